"""``measure-weld``'s toe figures against drawn truth: synthetic butt-weld profiles
(``simulator.weld_profiles``) with drawn toe radii and angles at several point spacings, with the
real scans' noise, spikes and dropouts. Per spacing, radius and angle (both toes of ``--n``
profiles): how many toes resolve their radius, the median error of the radius reported
(resolved toes) and of the fitted radius (all toes: the bias), whether every "below X" holds
(true radius <= X) and the median X, the median and worst toe-angle error.

    .venv/bin/python bench/bench_weld_profiles.py [--n 6] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from flows.scan_weld import profile_settings  # noqa: E402 - after the path is set
from schemas.profile_weld import MeasureWeldConfig  # noqa: E402
from simulator.weld_profiles import REAL_SCAN_NOISE, draw_butt_profile  # noqa: E402
from tasks.profile_weld import measure_profile  # noqa: E402

RADII_MM = (0.2, 0.3, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0)
ANGLES_DEG = (10, 20, 30, 45, 60)
SPACINGS_MM = (0.02, 0.05, 0.1)


def measure_grid(n: int, spacings=SPACINGS_MM, radii=RADII_MM, angles=ANGLES_DEG, seed: int = 27) -> list[dict]:
    """One row per spacing, radius and angle (``n`` profiles, two toes each)."""
    settings = profile_settings(MeasureWeldConfig())
    rng = np.random.default_rng(seed)
    rows = []
    for spacing in spacings:
        for r in radii:
            for angle in angles:
                rep, fitted, below, ang, pos = [], [], [], [], []
                for _ in range(n):
                    u, h, half = draw_butt_profile(toe_radius_mm=r, toe_angle_deg=angle, spacing_mm=spacing,
                                                   noise=REAL_SCAN_NOISE, rng=rng)
                    res = measure_profile(u, h, settings=settings, treated=False, line="w", position_mm=0.0,
                                          to_frame=lambda a, b: (a, 0.0, b))
                    for sign, toe in zip((-1, 1), res.toes):
                        if toe.fit is None:
                            continue
                        fitted.append(toe.radius_fitted.value)
                        ang.append(toe.fit.flank_angle_deg.value - angle)
                        pos.append(toe.fit.position_u_mm - sign * half)
                        if toe.radius_below_mm is None:
                            rep.append(toe.fit.notch_radius.value - r)
                        else:
                            below.append(toe.radius_below_mm)
                rows.append({
                    "spacing_mm": spacing, "radius_mm": r, "angle_deg": angle, "toes": 2 * n, "measured": len(ang),
                    "resolved": len(rep),
                    "radius_error_median_mm": float(np.median(rep)) if rep else None,
                    "radius_error_worst_mm": float(max(rep, key=abs)) if rep else None,
                    "fitted_bias_mm": float(np.median(fitted) - r) if fitted else None,
                    "below_x_hold": int(sum(x >= r for x in below)), "below_x": len(below),
                    "below_x_median_mm": float(np.median(below)) if below else None,
                    "angle_error_median_deg": float(np.median(ang)) if ang else None,
                    "angle_error_worst_deg": float(max(ang, key=abs)) if ang else None,
                    "position_error_median_mm": float(np.median(pos)) if pos else None})
    return rows


def _f(x, d=3):
    return "-" if x is None else f"{x:+.{d}f}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=6, help="profiles per cell (two toes each)")
    parser.add_argument("--spacing", type=float, nargs="+", default=SPACINGS_MM, help="mm")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    rows = measure_grid(args.n, spacings=tuple(args.spacing))
    print("| spacing mm | r mm | angle deg | resolved | r error median (worst) mm | fitted r bias mm | below X holds "
          "| X median mm | angle error median (worst) deg |")
    print("|---|---|---|---|---|---|---|---|---|")
    for w in rows:
        print(f"| {w['spacing_mm']} | {w['radius_mm']} | {w['angle_deg']} | {w['resolved']}/{w['measured']} | "
              f"{_f(w['radius_error_median_mm'])} ({_f(w['radius_error_worst_mm'])}) | {_f(w['fitted_bias_mm'])} | "
              f"{w['below_x_hold']}/{w['below_x']} | {_f(w['below_x_median_mm'], 2)} | "
              f"{_f(w['angle_error_median_deg'], 2)} ({_f(w['angle_error_worst_deg'], 2)}) |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
