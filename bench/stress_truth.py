"""The stress stage against the truth: a finished run's stress sections of a simulated dog-bone,
T-joint or cruciform, and the same sections of the simulator's true surface through the same code
(outline, meshing, solver, peaks), toe by toe.

    .venv/bin/python bench/stress_truth.py RUN_FOLDER SAMPLE_FOLDER [--notch] [--stress DIR]

The truth is the surface the simulator drew (``simulator.evaluate.true_specimen``: exact heights,
not ``truth/specimen.ply``'s vertices, which hold a toe of 0.46 mm radius on ~5 points on the ci
preset), sampled every 0.01 mm along the run's section planes, put where the run's specimen frame
has it (the stickers fit the true frame to the run's: ``simulator.evaluate.fit_gauge``), read
without smoothing (bins of 0.02 mm) and meshed, pulled and read at the run's toes exactly as the
stage does. A T-joint's true section (``simulator.tjoint.TJoint.section``: the drawn outline,
fillets rounded at their toes, every 0.01 mm) is read the same way (``tee_profile``, its roots
the drawn ones; a cruciform's lower stem's roots too). Prints each toe's factors and the differences; writes nothing."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

import tasks  # noqa: F401  (pymeshlab first: tasks/__init__.py)
from accuracy import StageFolder, stage_folder
from data_catalog.manifests import load_manifest
from flows.stages.outputs import REFINED, STRESS_SUMMARY
from flows.stages.placement import weld_frame
from flows.stages.stress import notch_mesh
from schemas.reconstruction import ReconstructionConfig
from simulator.evaluate import fit_gauge, true_specimen, true_tjoint
from tasks.frames import apply, invert, rotate
from tasks.plate_section import (SectionFrame, plate_profile, profile_section, rounded_notches, rounded_tee, tee_profile,
                                 tee_section)
from tasks.section_model import SectionMeshSettings, mesh_sections, peaks_near, pull_sections

__all__ = ["true_factors", "compare"]


def true_factors(run: Path, sample: Path, *, notch: bool = False, stress: Path | None = None,
                 config: ReconstructionConfig | None = None) -> tuple[list[list[float | None]], list[list[float | None]]]:
    """(the run's factors, the truth's) per section and toe, in stress.json's order; ``notch``: the
    notch factors (the run's stress stage made with ``stress.notch_stress``; the true outline
    rounded the same way). ``stress``: the stress stage's folder (default: the run's); ``config``:
    the settings it was made with (default: the run's published ones)."""
    summary = STRESS_SUMMARY.read(StageFolder(stress) if stress else stage_folder(run, "stress"))
    if config is None:
        config = ReconstructionConfig.model_validate(json.loads((Path(run) / "results" / "config.json").read_text()))
    s = config.stress
    manifest = load_manifest(Path(sample) / "manifest.json")
    refined = REFINED.read(stage_folder(run, "refine"))
    positions = refined.track_positions_mm
    G = fit_gauge(sample, positions[refined.specimen_track], positions).T_recon_specimen  # true -> common
    T = weld_frame(manifest, np.asarray(refined.T_common_pass))  # the run's specimen frame -> common
    run_to_true, true_to_run = invert(G) @ T, invert(T) @ G
    tee = manifest.specimen.kind in ("t-joint", "cruciform")
    specimen = true_tjoint(sample) if tee else true_specimen(sample)
    half = specimen.config.length_mm / 2 if not tee else specimen.config.base_length_mm / 2
    x = np.arange(-half, half + 1e-9, 0.01)
    lines = {line.name: line for line in load_geometry_lines(run)}
    planes, fine = [], []
    for section in summary.sections:
        line = lines[summary.driving_line]
        up, across = np.asarray(line.face_normal), np.asarray(line.across)
        along = np.cross(across, up)
        along /= np.linalg.norm(along)
        frame = SectionFrame(np.asarray(section.origin_specimen_mm), across, up, along)
        # the plane in the true frame: y where it crosses each x (it runs across y, the weld's direction)
        o, n = apply(run_to_true, frame.origin[None])[0], rotate(run_to_true, frame.along[None])[0]
        toes = np.array([[(np.asarray(t.toe_specimen_mm) - frame.origin) @ across,
                          (np.asarray(t.toe_specimen_mm) - frame.origin) @ up] for t in section.toes])
        if tee:
            outline, outward = specimen.section(float(o[1]), 0.01)
            y = o[1] - (n[0] * (outline[:, 0] - o[0])) / n[1]
            points = apply(true_to_run, np.c_[outline[:, 0], y, outline[:, 1]])
            normals = rotate(true_to_run, np.c_[outward[:, 0], np.zeros(len(y)), outward[:, 1]])
            tj = specimen.config

            def roots_on(face: float) -> dict[int, np.ndarray]:  # the drawn roots on the base's face (+1 up, -1 down)
                roots = {}
                for side in (-1, 1):
                    root = apply(true_to_run, np.array([[side * tj.stem_thickness_mm / 2, o[1],
                                                         face * tj.base_thickness_mm / 2]]))[0]
                    rel = root - frame.origin
                    roots[1 if rel @ across > 0 else -1] = np.array([rel @ across, rel @ up])
                return roots

            # the run's up is the driving line's face's: the drawn roots on the face it points out of first
            face = 1.0 if rotate(run_to_true, up[None])[0][2] > 0 else -1.0
            profile = tee_profile(points, normals, frame, roots_mm=roots_on(face), stem_cut_mm=s.stem_cut_mm,
                                  half_width_mm=0.05, bin_mm=0.02, smooth_mm=0.0,
                                  roots_below_mm=roots_on(-face) if tj.stems == "both" else None)
            if notch:
                profile = rounded_tee(profile, summary.notch_radius_mm)
            planes.append((profile.plate, tee_section(profile, cut_mm=s.cut_mm, fine_mm=toes)))
            fine.append(toes)
            continue
        y = o[1] - (n[0] * (x - o[0])) / n[1]
        top, bottom = specimen.top_z(x, y), specimen.bottom_z(x, y)
        points = apply(true_to_run, np.r_[np.c_[x, y, top], np.c_[x, y, bottom]])
        normals = rotate(true_to_run, np.r_[np.tile([0.0, 0.0, 1.0], (len(x), 1)), np.tile([0.0, 0.0, -1.0], (len(x), 1))])
        profile = plate_profile(points, normals, frame, half_width_mm=0.05, bin_mm=0.02, smooth_mm=0.0)
        if notch:
            profile = rounded_notches(profile, summary.notch_radius_mm)
        planes.append((profile, profile_section(profile, cut_mm=s.cut_mm, fine_mm=toes)))
        fine.append(toes)
    settings = SectionMeshSettings(fine_size_mm=s.toe_size_mm, fine_reach_mm=s.toe_zone_mm, size_mm=s.size_mm,
                                   growth=s.growth)
    reach = s.peak_reach_mm
    if notch:  # as the stage meshes and reads its rounded sections, at the radius it used
        settings, reach = notch_mesh(s.model_copy(update={"notch_radius_mm": summary.notch_radius_mm}))
    solutions = pull_sections(mesh_sections([p for _, p in planes], settings, timeout_s=s.timeout_s), timeout_s=s.timeout_s,
                              max_nodes_per_run=s.max_nodes_per_solve)
    ours, truth = [], []
    near, far = s.plate_window_mm
    for section, (profile, _), toes, solution in zip(summary.sections, planes, fine, solutions):
        peaks = peaks_near(solution, toes, reach)
        row = []
        for toe, xy, (peak, _) in zip(section.toes, toes, peaks):
            sign = -1.0 if xy[0] < 0 else 1.0
            thickness = profile.thickness_mm(sign * near, sign * far)
            row.append(peak / (solution.force_n / thickness) if math.isfinite(peak) else None)
        truth.append(row)
        ours.append([t.notch_factor if notch else t.factor for t in section.toes])
    return ours, truth


def load_geometry_lines(run: Path):
    from flows.stages.outputs import WELD_GEOMETRY

    return WELD_GEOMETRY.read(stage_folder(run, "weld")).lines


# a toe whose true factor is under this carries next to no load in the case: a T-joint's stem toes
# (~0.005 of the nominal stress), a cruciform's (up to 0.23: its stems, on both faces, share a little
# of the base's stretch), against base toes of 1.3 and more; their relative differences say nothing
_UNLOADED = 0.5


def compare(run: Path, sample: Path, *, notch: bool = False, stress: Path | None = None,
            config: ReconstructionConfig | None = None) -> dict:
    """Per toe line: the run's and the truth's hot spot, their difference and how far apart along
    the weld, and the truth's factor in the run's hot-spot section against the truth's hot spot
    (``truth_there``: 0 where they are the same section; how much a hot spot put in the wrong
    section of a nearly even weld misses by); and over every section and toe the median and worst difference (``notch``: of the
    notch factors). Toes the load does not reach (true factor under 0.5: a T-joint's or a
    cruciform's stem toes when its base is pulled) are listed apart (``unloaded``), their largest factors only."""
    summary = STRESS_SUMMARY.read(StageFolder(stress) if stress else stage_folder(run, "stress"))
    ours, truth = true_factors(run, sample, notch=notch, stress=stress, config=config)
    by_toe: dict[tuple[str, str], list[tuple[float, float, float]]] = {}
    differences = []
    for section, o_row, t_row in zip(summary.sections, ours, truth):
        for toe, o, t in zip(section.toes, o_row, t_row):
            if o is None or t is None:
                continue
            by_toe.setdefault((toe.line, toe.side), []).append((section.position_mm, o, t))
    toes, unloaded = {}, {}
    for key, rows in sorted(by_toe.items()):
        if max(r[2] for r in rows) < _UNLOADED:
            unloaded[f"{key[0]} {key[1]}"] = {"ours": round(max(r[1] for r in rows), 4),
                                              "truth": round(max(r[2] for r in rows), 4)}
            del by_toe[key]
        else:
            differences += [o / t - 1 for _, o, t in rows]
    for (line, side), rows in sorted(by_toe.items()):
        o_at, o_hot, t_there = max(rows, key=lambda r: r[1])
        t_at, _, t_hot = max(rows, key=lambda r: r[2])
        toes[f"{line} {side}"] = {"ours": round(o_hot, 4), "truth": round(t_hot, 4),
                                  "difference": round(o_hot / t_hot - 1, 4), "apart_mm": round(abs(o_at - t_at), 3),
                                  "truth_there": round(t_there / t_hot - 1, 4), "sections": len(rows)}
    d = np.abs(np.array(differences))
    return {"toes": toes, "median_difference": round(float(np.median(d)), 4), "worst_difference": round(float(d.max()), 4),
            "toe_sections": len(d), "unloaded": unloaded}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("sample", type=Path)
    parser.add_argument("--notch", action="store_true", help="the notch factors (a run made with stress.notch_stress)")
    parser.add_argument("--stress", type=Path, help="the stress stage's folder, when not the run's (bench_fe_stages --keep)")
    args = parser.parse_args()
    print(json.dumps(compare(args.run, args.sample, notch=args.notch, stress=args.stress), indent=1))


if __name__ == "__main__":
    main()
