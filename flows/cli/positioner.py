"""``weldrecon calibrate-positioner RUN_DIR... --out FILE.yaml``: the positioner's axis from the
stickers of reconstructed runs of parts it turned (``flows.positioner``)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["add_calibrate_positioner"]


def add_calibrate_positioner(sub) -> None:
    cal = sub.add_parser("calibrate-positioner", help="the positioner's turning axis from the registered stickers of "
                         "runs of parts it turned between setups")
    cal.add_argument("runs", nargs="+", metavar="RUN_DIR", help="run folders of `weldrecon reconstruct` (stage refine "
                     "finished) of samples whose later setups the positioner turned")
    cal.add_argument("--out", required=True, metavar="FILE.yaml", help="new file: the axis as a part config's "
                     "positioner (for simulate/plan --config, or a manifest's setups[].positioner)")
    cal.set_defaults(func=_cmd_calibrate)


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from data_catalog.atomic import atomic_write_text
    from flows.positioner import calibration_yaml, mean_axis, run_turns

    out = Path(args.out)
    if out.exists():
        raise ValueError(f"--out {out} already exists; choose a new file (nothing was written)")
    turns = [t for run in args.runs for t in run_turns(Path(run))]
    point, direction, angle, spread = mean_axis(turns)
    for t in turns:
        tilt, mm = spread[f"{t.run} {t.setup}"]
        print(f"{t.run}: setup {t.setup} from {t.from_setup}: turned {t.angle_deg:.4f} deg about "
              f"({', '.join(f'{v:.4f}' for v in t.direction)}) through ({', '.join(f'{v:.3f}' for v in t.point_mm)}) mm; "
              f"{tilt:.4f} deg and {mm:.3f} mm from the mean axis")
    atomic_write_text(out, calibration_yaml(point, direction, angle, [str(r) for r in args.runs]))
    print(f"{out}: axis through ({', '.join(f'{v:.3f}' for v in point)}) mm along "
          f"({', '.join(f'{v:.6f}' for v in direction)}), turn {angle:.4f} deg, from {len(turns)} turn(s)",
          file=sys.stdout)
    return 0
