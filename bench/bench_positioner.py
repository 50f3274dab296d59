"""A sample turned by the cell's positioner (``weldrecon plan PART --positioner``, or a preset with
``positioner:`` in its config), reconstructed: the positioner's axis against the truth.

    .venv/bin/python bench/bench_positioner.py SAMPLE_DIR RUN_DIR [--json OUT.json]

For each setup turned by the positioner: the axis as calibrated (the manifest's) and as the
registered stickers give it (the registration summary's ``turn``; and again from the refined
poses), each against the true axis (``truth/truth.json`` ``positioner``): the angle between the
axes' directions, the distance between the axes at the part (from the true axis's point nearest
the part's origin to the other line), the turn's angle off the true one, and the turn's largest
displacement of a point of the part (its bounding box's corners) from where the true turn puts it.
With the pass misalignment against the truth (``simulator.evaluate.pass_misalignment``: targets
alone and refined). The run needs stage refine (``--stop-after refine`` will do).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def axis_error(point, direction, angle, true) -> dict:
    """An axis (a point, a direction) and a turn's angle against the true ones: the angle between
    the directions (deg), the distance from the true axis's point to the line (mm), the angle off;
    ``T``: the turn they make."""
    from tasks.frames import turn_about_axis

    d, td = np.asarray(direction, float), np.asarray(true.axis_direction, float)
    d, td = d / np.linalg.norm(d), td / np.linalg.norm(td)
    tilt = float(np.degrees(np.arccos(np.clip(abs(d @ td), -1, 1))))
    p, tp = np.asarray(point, float), np.asarray(true.axis_point_mm, float)
    off = (tp - p) - ((tp - p) @ d) * d
    return {"direction_deg": round(tilt, 5), "offset_mm": round(float(np.linalg.norm(off)), 4),
            "angle_deg": round(float(angle - true.angle_deg), 5),
            "T": turn_about_axis(point, direction, angle)}


def evaluate(sample: Path, run: Path) -> dict:
    from bench.accuracy import pass_misalignments, stage_folder
    from data_catalog.manifests import load_manifest
    from data_catalog.truth import read_truth
    from flows.stages.outputs import REFINED, REGISTRATION_SUMMARY
    from tasks.frames import screw_axis_as, turn_about_axis
    from tasks.graph import setup_turn

    manifest = load_manifest(sample)
    truth = read_truth(sample / "truth" / "truth.json")
    if truth.positioner is None:
        raise SystemExit(f"{sample}: the truth has no positioner: the part was turned by hand")
    true = truth.positioner
    T_true = turn_about_axis(true.axis_point_mm, true.axis_direction, true.angle_deg)
    lo, hi = manifest.specimen.bounds_mm()
    T0 = np.asarray(truth.T_world_specimen[true.from_setup])
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    corners = corners @ T0[:3, :3].T + T0[:3, 3]

    def moved(T) -> float:
        return round(float(np.linalg.norm(corners @ (T[:3, :3] - T_true[:3, :3]).T + (T[:3, 3] - T_true[:3, 3]),
                                          axis=1).max()), 4)

    setup = next(s for s in manifest.setups if s.name == true.setup)
    cal = setup.positioner
    out = {"sample": manifest.sample_id, "true_axis": true.model_dump()}
    calibrated = axis_error(cal.axis_point_mm, cal.axis_direction, cal.angle_deg, true)
    calibrated["part_moved_mm"] = moved(calibrated.pop("T"))
    out["calibrated (the manifest's)"] = calibrated
    summary = REGISTRATION_SUMMARY.read(stage_folder(run, "registration"))
    evidence = next(e for e in summary.between_setups if e.b == true.setup)
    registered = axis_error(evidence.turn.axis_point_mm, evidence.turn.axis_direction, evidence.turn.angle_deg, true)
    registered["part_moved_mm"] = moved(registered.pop("T"))
    out["from the stickers, targets alone (registration summary)"] = registered
    out["stickers matched on the prior"] = evidence.targets
    out["prior against the stickers' match (deg, mm)"] = (evidence.prior_difference_deg, evidence.prior_difference_mm)
    setups = [s for s, _ in manifest.passes()]
    M = setup_turn(setups, np.asarray(REFINED.read(stage_folder(run, "refine")).T_common_pass), true.from_setup,
                   true.setup)
    point, direction, angle, _ = screw_axis_as(M, cal.axis_direction, cal.angle_deg, cal.axis_point_mm)
    refined = axis_error(point, direction, angle, true)
    refined["part_moved_mm"] = moved(M)
    refined.pop("T")
    out["from the refined poses"] = refined
    for name, m in pass_misalignments(sample, run).items():
        worst = int(np.nanargmax(m.max_mm))
        out[f"pass misalignment, {name}"] = {"worst_um": round(1000 * float(m.max_mm[worst]), 1),
                                             "worst_pass": m.pass_ids[worst],
                                             "median_of_pass_medians_um": round(1000 * float(np.nanmedian(m.median_mm)), 1)}
    return out


def main() -> int:
    from bench.accuracy import emit

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sample", type=Path)
    parser.add_argument("run", type=Path)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    emit(evaluate(args.sample, args.run), args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
