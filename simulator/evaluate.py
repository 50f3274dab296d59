"""Reconstructions measured against the simulator's ground truth (tests and benchmarks only;
the pipeline never reads truth).

The reconstruction lives in its own frame (the first pass's coarse frame); the *gauge* is the
rigid transform from the specimen frame into it, fitted on the true specimen sticker centres
against the registered specimen targets.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from data_catalog.manifests import load_manifest
from data_catalog.passes import read_pass
from data_catalog.truth import (FILLET_TRUTH_NAME, TRUTH_DIR, WELD_TRUTH_NAME, read_fillet_truth, read_truth,
                                read_truth_pass, read_weld_truth)
from schemas.truth import Material, PointLabel
from schemas.weld_document import WeldGeometry
from tasks.ingest import profile_points, sensor_poses
from tasks.matching import kabsch, match_rotation_invariant

__all__ = ["STICKER_LIFT_MM", "true_sticker_centres", "Gauge", "fit_gauge", "PassMisalignment",
           "pass_misalignment", "T_true_specimen_nominal", "weld_errors", "fillet_errors", "summarise_weld_errors",
           "true_specimen", "true_tjoint"]

STICKER_LIFT_MM = 0.1  # the paper sticker's thickness: its visible centre is this far off the surface
_SPECIMEN = (Material.STEEL, Material.GROUND, Material.STICKER)


@dataclass(frozen=True)
class Gauge:
    T_recon_specimen: np.ndarray  # (4, 4)
    n_targets: int  # true specimen stickers matched to registered targets
    n_true: int  # true specimen stickers
    residual_mm: np.ndarray  # (n_targets,) after the fit


def true_sticker_centres(truth) -> np.ndarray:
    """(k, 3) the visible centres (top of the paper) of the true specimen stickers, specimen frame."""
    return np.array([np.array(s.centre_mm) + STICKER_LIFT_MM * np.array(s.normal)
                     for s in truth.stickers if s.on == "specimen"])


def fit_gauge(sample_dir: Path, specimen_targets_mm: np.ndarray, all_targets_mm: np.ndarray | None = None, *,
              match_mm: float = 1.0) -> Gauge:
    """Pair the registered targets with the true specimen stickers and fit the rigid transform.
    ``specimen_targets_mm``: targets known to be on the specimen (seen in both setups), for a
    rough fit; ``all_targets_mm``: every registered target, paired by nearness after it."""
    truth = read_truth(Path(sample_dir) / TRUTH_DIR / "truth.json")
    true = true_sticker_centres(truth)
    found = specimen_targets_mm if all_targets_mm is None else all_targets_mm
    T = match_rotation_invariant(specimen_targets_mm, true).T_a_b  # rough; then nearest pairs, refit
    ok = np.zeros(len(found), bool)
    k = np.zeros(len(found), int)
    for _ in range(3):
        moved = true @ T[:3, :3].T + T[:3, 3]
        d = np.linalg.norm(found[:, None] - moved[None], axis=-1)
        k = d.argmin(axis=1)
        ok = d.min(axis=1) < match_mm
        T = kabsch(true[k[ok]], found[ok])
    moved = true[k[ok]] @ T[:3, :3].T + T[:3, 3]
    return Gauge(T_recon_specimen=T, n_targets=int(ok.sum()), n_true=len(true),
                 residual_mm=np.linalg.norm(moved - found[ok], axis=1))


@dataclass(frozen=True)
class PassMisalignment:
    """Per pass, over the specimen surface it measured: the largest and the median distance
    between where the reconstruction puts a measured point and where that point truly is, after
    ``T_recon_specimen`` (the gauge: given, or else the rigid fit over all those points)."""

    pass_ids: list[str]
    max_mm: np.ndarray
    median_mm: np.ndarray
    T_recon_specimen: np.ndarray


def pass_misalignment(sample_dir: Path, T_common_pass: np.ndarray, gauge: Gauge | None = None, *,
                      every: int = 10) -> PassMisalignment:
    """``T_common_pass`` (n, 4, 4) maps each pass's coarse points (the logged robot poses) into the
    reconstruction; truth says where each of those points really is on the specimen. Without a
    gauge, the reconstruction's frame is fitted to the truth over all points, so the figures are
    the passes' misalignment alone, free of any error in where the targets put the whole."""
    sample_dir = Path(sample_dir)
    manifest = load_manifest(sample_dir)
    truth = read_truth(sample_dir / TRUTH_DIR / "truth.json")
    ids, ours, true = [], [], []
    for k, (setup, entry) in enumerate(manifest.passes()):
        data = read_pass(sample_dir / entry.file)
        tp = read_truth_pass(sample_dir / TRUTH_DIR / "passes" / f"{entry.pass_id}.zarr")
        T_world_sensor = sensor_poses(manifest.scanner.T_flange_sensor, timestamp_s=data.timestamp_s,
                                      T_world_flange=data.T_world_flange, motion=entry.nominal_motion)
        coarse = profile_points(data.x_mm, data.z_mm, T_world_sensor)
        on_specimen = np.isin(tp.material, _SPECIMEN) & (tp.label == PointLabel.VALID)
        p = coarse[on_specimen][::every]
        E = np.array(next(t.T_nominal_true for t in truth.passes if t.pass_id == entry.pass_id))
        M = np.linalg.inv(np.array(truth.T_world_specimen[setup])) @ E  # coarse -> true, specimen frame
        ids.append(entry.pass_id)
        ours.append(p @ T_common_pass[k][:3, :3].T + T_common_pass[k][:3, 3])
        true.append(p @ M[:3, :3].T + M[:3, 3])
    G = gauge.T_recon_specimen if gauge is not None else kabsch(np.concatenate(true), np.concatenate(ours))
    dist = [np.linalg.norm(o - (t @ G[:3, :3].T + G[:3, 3]), axis=1) for o, t in zip(ours, true)]
    return PassMisalignment(ids, np.array([d.max() if len(d) else np.nan for d in dist]),
                            np.array([np.median(d) if len(d) else np.nan for d in dist]), G)


def T_true_specimen_nominal(sample_dir: Path, manifest, refined) -> np.ndarray:
    """(4, 4): the specimen frame stage ``weld`` measures in (the first setup's nominal placement
    through its first pass's refined pose) into the true specimen frame, through the gauge.
    ``refined``: stage refine's ``RefinedPoses``."""
    T_common_pass = np.asarray(refined.T_common_pass[...])
    names = [e.pass_id for _, e in manifest.passes()]
    setup = next(s for s in manifest.setups if s.T_world_specimen_nominal is not None)
    T_common_nominal = T_common_pass[names.index(setup.passes[0].pass_id)] @ np.asarray(setup.T_world_specimen_nominal)
    tracks = np.asarray(refined.track_positions_mm[...])
    gauge = fit_gauge(sample_dir, tracks[np.asarray(refined.specimen_track[...]).astype(bool)], tracks)
    return np.linalg.inv(gauge.T_recon_specimen) @ T_common_nominal


def weld_errors(sample: Path, geometry: WeldGeometry, T_true_specimen_nominal: np.ndarray) -> dict[str, list[tuple[float, float]]]:
    """Stage weld's ``weld_geometry.json`` (``geometry``) against ``truth/weld_sections.json``:
    figure -> [(measured - true, true)] over every measured section and toe. Each section is
    placed in the true specimen frame by ``T_true_specimen_nominal`` and compared with the drawn
    cap there (interpolated along y); toes ``minus``/``plus`` are the drawn (-x, +x) ones."""
    truth = read_weld_truth(Path(sample) / TRUTH_DIR / WELD_TRUTH_NAME)
    by_side: dict[str, list] = {}
    for s in truth.sections:
        by_side.setdefault(s.side, []).append(s)
    errors: dict[str, list[tuple[float, float]]] = {}

    def add(name, measured, true):
        if measured is not None and true is not None and np.isfinite(measured):
            errors.setdefault(name, []).append((float(measured) - float(true), float(true)))

    R, t = T_true_specimen_nominal[:3, :3], T_true_specimen_nominal[:3, 3]
    for sec in geometry.sections:
        rows = by_side.get(sec.line)
        if not rows or sec.reinforcement_height_mm.value is None:
            continue
        y = float((R @ np.asarray(sec.centre_specimen_mm) + t)[1])
        ys = np.array([r.y_mm for r in rows])

        def at(get):
            return float(np.interp(y, ys, [get(r) for r in rows]))

        add("reinforcement_height_mm", sec.reinforcement_height_mm.value, at(lambda r: r.peak_height_mm))
        treated = any(toe is not None and toe.groove is not None for _, toe in sec.toes.sides())
        if not treated:  # a treated weld's width is between where the grooves meet it, not the drawn toes
            add("reinforcement_width_mm", sec.reinforcement_width_mm.value, at(lambda r: r.width_mm))
        for k, (side, toe) in enumerate(sec.toes.sides()):
            if toe is None:
                continue
            groove = toe.groove
            if groove is None:  # a treated toe's drawn flank is cut away by the groove: not compared
                add("flank_angle_deg", toe.flank_angle_deg.value, at(lambda r: r.flank_angle_deg[k]))
                true_r = at(lambda r: r.toe_radius_mm[k])
                add("toe_radius_mm", toe.toe_radius_mm.value, true_r)
                if true_r >= 0.5:
                    add("toe_radius_mm (r >= 0.5)", toe.toe_radius_mm.value, true_r)
                add("undercut_depth_mm", toe.undercut_depth_mm.value, at(lambda r: r.undercut_depth_mm[k]))
            elif rows[0].groove_depth_mm is not None:
                add("groove_depth_mm", groove.depth_mm.value, at(lambda r: r.groove_depth_mm[k]))
                add("groove_width_mm", groove.width_mm.value, at(lambda r: r.groove_width_mm[k]))
                add("groove_radius_mm (toe radius, treated)", groove.radius_mm.value,
                    at(lambda r: r.groove_radius_mm[k]))
    return errors


def fillet_errors(sample: Path, geometry: WeldGeometry, T_true_specimen_nominal: np.ndarray, *,
                  lines: Collection[str] | None = None) -> dict[str, list[tuple[float, float]]]:
    """A fillet weld's ``weld_geometry.json`` against ``truth/fillet_weld.json`` (a T-joint's or
    a cruciform's): figure -> [(measured - true, true)] over every measured section and toe (of
    the weld lines ``lines`` only, when given: e.g. a cruciform's on one face of its base plate),
    each section's root placed in the true specimen frame and compared with the drawn fillet of
    its line there (interpolated along y)."""
    truth = read_fillet_truth(Path(sample) / TRUTH_DIR / FILLET_TRUTH_NAME)
    by_line: dict[str, list] = {}
    for s in truth.sections:
        by_line.setdefault(s.weld, []).append(s)
    errors: dict[str, list[tuple[float, float]]] = {}

    def add(name, measured, true):
        if measured is not None and np.isfinite(measured):
            errors.setdefault(name, []).append((float(measured) - float(true), float(true)))

    R, t = T_true_specimen_nominal[:3, :3], T_true_specimen_nominal[:3, 3]
    for sec in geometry.sections:
        rows = by_line.get(sec.line)
        if not rows or (lines is not None and sec.line not in lines):
            continue
        y = float((R @ np.asarray(sec.centre_specimen_mm) + t)[1])
        ys = np.array([r.y_mm for r in rows])

        def at(get):
            return float(np.interp(y, ys, [get(r) for r in rows]))

        for name, true in (("leg_base_mm", at(lambda r: r.leg_base_mm)), ("leg_stem_mm", at(lambda r: r.leg_stem_mm)),
                           ("throat_mm", at(lambda r: r.throat_mm)), ("convexity_mm", at(lambda r: r.convexity_mm))):
            add(name, sec.figure(name).value, true)
        for k, (side, toe) in enumerate(sec.toes.sides()):
            if toe is None:
                continue
            true_r = at(lambda r: r.toe_radius_mm[k])
            add(f"toe_radius_mm ({side})", toe.toe_radius_mm.value, true_r)
            if true_r >= 0.5:
                add("toe_radius_mm (r >= 0.5)", toe.toe_radius_mm.value, true_r)
            add(f"toe_angle_deg ({side})", toe.flank_angle_deg.value, at(lambda r: r.toe_angle_deg[k]))
            add(f"toe angle against the face past the rounding ({side})", toe.flank_angle_deg.value,
                at(lambda r: r.face_angle_deg[k]))
    return errors


def summarise_weld_errors(errors: dict[str, list[tuple[float, float]]]) -> dict[str, dict[str, float]]:
    out = {}
    for name, pairs in sorted(errors.items()):
        e = np.array([p[0] for p in pairs])
        out[name] = {"n": int(len(e)), "median_abs": round(float(np.median(np.abs(e))), 4),
                     "p90_abs": round(float(np.percentile(np.abs(e), 90)), 4),
                     "worst_abs": round(float(np.abs(e).max()), 4), "median_signed": round(float(np.median(e)), 4)}
    return out




def true_specimen(sample_dir: Path):
    """The simulated dog-bone of a sample as the simulator drew it (``simulator.specimen.Specimen``:
    its welds' height functions, its misalignment), drawn again from ``truth/simulation.json`` with
    the same seed: exact surface heights anywhere, where ``truth/specimen.ply`` holds them at its
    vertices only (a toe of 0.46 mm radius on ~5 vertices 0.08 mm apart on the ci preset)."""
    from schemas.simulation import SimulationConfig
    from simulator.specimen import build_specimen

    config = SimulationConfig.model_validate_json((Path(sample_dir) / TRUTH_DIR / "simulation.json").read_text())
    if config.tjoint is not None:
        raise ValueError(f"{sample_dir}: a T-joint sample; true_specimen draws the dog-bone only (true_tjoint: the T)")
    rng = np.random.default_rng(np.random.SeedSequence(config.seed).spawn(5)[0])
    return build_specimen(config.specimen, config.weld, config.mesh, rng)


def true_tjoint(sample_dir: Path):
    """The simulated T-joint or cruciform of a sample as the simulator drew it
    (``simulator.tjoint.TJoint``: its fillets' figures along y), drawn again from
    ``truth/simulation.json`` with the same seed."""
    from schemas.simulation import SimulationConfig
    from simulator.tjoint import build_tjoint

    config = SimulationConfig.model_validate_json((Path(sample_dir) / TRUTH_DIR / "simulation.json").read_text())
    if config.tjoint is None:
        raise ValueError(f"{sample_dir}: not a T-joint sample")
    rng = np.random.default_rng(np.random.SeedSequence(config.seed).spawn(5)[0])
    return build_tjoint(config.tjoint, config.weld, config.mesh, rng)
