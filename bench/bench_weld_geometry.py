"""The weld measured by stage ``weld`` against the simulator's drawn weld, section by section.

The sample is reconstructed in this process up to stage ``weld`` (earlier stages come from the
stage store under WORK when already there); each measured section is placed in the true
specimen frame (the gauge fitted on the stickers, ``simulator.evaluate.fit_gauge``) and compared
with ``truth/weld_sections.json`` at its position: toe radius (as welded: the fillet's; treated:
the groove's), flank angle, reinforcement height (the drawn profile's peak, ripple included),
groove depth, width and undercut. A treated toe's flank angle and the treated weld's width are not
compared: the drawn flank at the toe is cut away by the groove (the stage reports the flank just
above it, and the width between where the grooves meet the weld). Median and worst absolute error, and the median signed error.

    .venv/bin/python bench/bench_weld_geometry.py SAMPLE_DIR CONFIG.yaml WORK_DIR [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from data_catalog.manifests import load_manifest  # noqa: E402 - after the path is set
from data_catalog.stages import StageStore  # noqa: E402
from data_catalog.truth import TRUTH_DIR, WELD_TRUTH_NAME, read_weld_truth  # noqa: E402
from flows.preflight import load_config  # noqa: E402
from flows.stages import run_in_process  # noqa: E402
from flows.stages.outputs import REFINED, WELD_GEOMETRY  # noqa: E402
from simulator.evaluate import fit_gauge  # noqa: E402


def compare(sample: Path, geometry: dict, T_true_specimen_nominal: np.ndarray) -> dict[str, list[tuple[float, float]]]:
    """figure -> [(measured - true, true)] over every measured section and toe."""
    truth = read_weld_truth(sample / TRUTH_DIR / WELD_TRUTH_NAME)
    by_side: dict[str, list] = {}
    for s in truth.sections:
        by_side.setdefault(s.side, []).append(s)
    errors: dict[str, list[tuple[float, float]]] = {}

    def add(name, measured, true):
        if measured is not None and true is not None and np.isfinite(measured):
            errors.setdefault(name, []).append((float(measured) - float(true), float(true)))

    R, t = T_true_specimen_nominal[:3, :3], T_true_specimen_nominal[:3, 3]
    for sec in geometry["sections"]:
        rows = by_side.get(sec["line"])
        if not rows or sec["reinforcement_height_mm"]["value"] is None:
            continue
        y = float((R @ np.asarray(sec["centre_specimen_mm"]) + t)[1])
        ys = np.array([r.y_mm for r in rows])

        def at(get):
            return float(np.interp(y, ys, [get(r) for r in rows]))

        add("reinforcement_height_mm", sec["reinforcement_height_mm"]["value"], at(lambda r: r.peak_height_mm))
        treated = any(t is not None and t.get("groove") is not None for t in sec["toes"].values())
        if not treated:  # a treated weld's width is between where the grooves meet it, not the drawn toes
            add("reinforcement_width_mm", sec["reinforcement_width_mm"]["value"], at(lambda r: r.width_mm))
        for k, side in enumerate(("minus", "plus")):
            toe = sec["toes"][side]
            if toe is None:
                continue
            groove = toe.get("groove")
            if groove is None:  # a treated toe's drawn flank is cut away by the groove: not compared
                add("flank_angle_deg", toe["flank_angle_deg"]["value"], at(lambda r: r.flank_angle_deg[k]))
                true_r = at(lambda r: r.toe_radius_mm[k])
                add("toe_radius_mm", toe["toe_radius_mm"]["value"], true_r)
                if true_r >= 0.5:
                    add("toe_radius_mm (r >= 0.5)", toe["toe_radius_mm"]["value"], true_r)
                add("undercut_depth_mm", toe["undercut_depth_mm"]["value"], at(lambda r: r.undercut_depth_mm[k]))
            elif rows[0].groove_depth_mm is not None:
                add("groove_depth_mm", groove["depth_mm"]["value"], at(lambda r: r.groove_depth_mm[k]))
                add("groove_width_mm", groove["width_mm"]["value"], at(lambda r: r.groove_width_mm[k]))
                add("groove_radius_mm (toe radius, treated)", groove["radius_mm"]["value"],
                    at(lambda r: r.groove_radius_mm[k]))
    return errors


def summarise(errors: dict[str, list[tuple[float, float]]]) -> dict[str, dict[str, float]]:
    out = {}
    for name, pairs in sorted(errors.items()):
        e = np.array([p[0] for p in pairs])
        out[name] = {"n": int(len(e)), "median_abs": round(float(np.median(np.abs(e))), 4),
                     "p90_abs": round(float(np.percentile(np.abs(e), 90)), 4),
                     "worst_abs": round(float(np.abs(e).max()), 4), "median_signed": round(float(np.median(e)), 4)}
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sample", type=Path)
    parser.add_argument("config", type=Path)
    parser.add_argument("work", type=Path)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    manifest = load_manifest(args.sample)
    t0 = time.perf_counter()
    refs = run_in_process(store=StageStore(args.work), sample_dir=args.sample, manifest=manifest,
                          config=load_config(args.config), upto="weld")
    seconds = time.perf_counter() - t0
    geometry = WELD_GEOMETRY.read(refs["weld"])
    refined = REFINED.open(refs["refine"])
    T_common_pass = np.asarray(refined.T_common_pass[...])
    names = [e.pass_id for _, e in manifest.passes()]
    setup = next(s for s in manifest.setups if s.T_world_specimen_nominal is not None)
    T_common_nominal = T_common_pass[names.index(setup.passes[0].pass_id)] @ np.asarray(setup.T_world_specimen_nominal)
    tracks = np.asarray(refined.track_positions_mm[...])
    gauge = fit_gauge(args.sample, tracks[np.asarray(refined.specimen_track[...]).astype(bool)], tracks)
    T_true_nominal = np.linalg.inv(gauge.T_recon_specimen) @ T_common_nominal
    result = {"sample": manifest.sample_id, "treatment": geometry["treatment"],
              "sections": geometry.get("summary", {}).get("sections"), "verdict": geometry.get("summary", {}).get("verdict"),
              "weld_stage_seconds": refs["weld"].metrics.get("seconds"), "run_seconds": round(seconds, 1),
              "errors": summarise(compare(args.sample, geometry, T_true_nominal))}
    print(f"{result['sample']} ({result['treatment']}): {result['sections']} sections, weld stage "
          f"{result['weld_stage_seconds']} s, verdict {result['verdict']}")
    print(f"{'figure':42s} {'n':>5s} {'median |e|':>11s} {'p90 |e|':>9s} {'worst |e|':>10s} {'median e':>9s}")
    for name, s in result["errors"].items():
        print(f"{name:42s} {s['n']:5d} {s['median_abs']:11.4f} {s['p90_abs']:9.4f} {s['worst_abs']:10.4f} "
              f"{s['median_signed']:9.4f}")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
