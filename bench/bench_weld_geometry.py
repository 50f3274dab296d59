"""The weld measured by stage ``weld`` against the simulator's drawn weld, section by section.

The sample is reconstructed in this process up to stage ``weld`` (earlier stages come from the
stage store under WORK when already there); each measured section is placed in the true
specimen frame (the gauge fitted on the stickers, ``simulator.evaluate.fit_gauge``) and compared
with ``truth/weld_sections.json`` at its position: toe radius (as welded: the fillet's; treated:
the groove's), flank angle, reinforcement height (the drawn profile's peak, ripple included),
groove depth, width and undercut. A treated toe's flank angle and the treated weld's width are not
compared: the drawn flank at the toe is cut away by the groove (the stage reports the flank just
above it, and the width between where the grooves meet the weld). A T-joint's fillet welds are
compared with ``truth/fillet_weld.json``: legs, throat, convexity, each toe's radius and angle;
a cruciform's also face by face (``errors_by_face``: the fillets on the base plate's upper face,
z > 0, and on its lower face). Median and worst absolute error, and the median signed error.

    .venv/bin/python bench/bench_weld_geometry.py SAMPLE_DIR CONFIG.yaml WORK_DIR [--json OUT.json]

(an empty CONFIG, e.g. /dev/null: the default settings, as for the paper preset)
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from data_catalog.manifests import load_manifest  # noqa: E402 - after the path is set
from data_catalog.stages import StageStore  # noqa: E402
from flows.preflight import load_config  # noqa: E402
from flows.stages import run_in_process  # noqa: E402
from flows.stages.outputs import REFINED, WELD_GEOMETRY  # noqa: E402
from data_catalog.truth import FILLET_TRUTH_NAME, TRUTH_DIR  # noqa: E402
from simulator.evaluate import T_true_specimen_nominal, fillet_errors, summarise_weld_errors, weld_errors  # noqa: E402


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
                          config=load_config(args.config if args.config.stat().st_size else None), upto="weld")
    seconds = time.perf_counter() - t0
    geometry = WELD_GEOMETRY.read(refs["weld"])
    T_true_nominal = T_true_specimen_nominal(args.sample, manifest, REFINED.open(refs["refine"]))
    fillet = (args.sample / TRUTH_DIR / FILLET_TRUTH_NAME).exists()
    errors = (fillet_errors if fillet else weld_errors)(args.sample, geometry, T_true_nominal)
    summary = geometry.summary
    result = {"sample": manifest.sample_id, "treatment": geometry.treatment,
              "sections": None if summary is None else summary.sections,
              "verdict": None if summary is None else summary.verdict,
              "weld_stage_seconds": refs["weld"].metrics.get("seconds"), "run_seconds": round(seconds, 1),
              "errors": summarise_weld_errors(errors)}
    if fillet and manifest.specimen.kind == "cruciform":
        faces = {"upper face": [line.name for line in manifest.weld_lines() if line.points_mm[0][2] > 0],
                 "lower face": [line.name for line in manifest.weld_lines() if line.points_mm[0][2] < 0]}
        result["errors_by_face"] = {face: summarise_weld_errors(fillet_errors(args.sample, geometry, T_true_nominal,
                                                                              lines=names))
                                    for face, names in faces.items()}
    print(f"{result['sample']} ({result['treatment']}): {result['sections']} sections, weld stage "
          f"{result['weld_stage_seconds']} s, verdict {result['verdict']}")
    print(f"{'figure':42s} {'n':>5s} {'median |e|':>11s} {'p90 |e|':>9s} {'worst |e|':>10s} {'median e':>9s}")
    for name, s in result["errors"].items():
        print(f"{name:42s} {s['n']:5d} {s['median_abs']:11.4f} {s['p90_abs']:9.4f} {s['worst_abs']:10.4f} "
              f"{s['median_signed']:9.4f}")
    for face, figures in result.get("errors_by_face", {}).items():
        print(f"-- {face}")
        for name, s in figures.items():
            print(f"{name:42s} {s['n']:5d} {s['median_abs']:11.4f} {s['p90_abs']:9.4f} {s['worst_abs']:10.4f} "
                  f"{s['median_signed']:9.4f}")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
