"""Sections of a real profile scan drawn for marking the toes by eye (``tests/data/realweld_marks``):
per profile one PNG, each toe zoomed (2 mm across, the height over the plate exaggerated about
1.7 times), a 0.05 mm grid to read x off. Nothing measured is drawn, so the marks owe nothing to either tool.

Per side of a profile (split at the top of its 7-point running median): the plate's line through
the outer 8 mm of that side; the window runs from 1.5 mm on the plate side to 0.5 mm on the weld
side of the first point from which the surface stands 0.3 mm over that line for 0.3 mm (a crude
guess, only to place the window; the scan's edge has lone high points).

    .venv/bin/python bench/draw_mark_sections.py SCAN.xyz OUT_DIR --y 16.5 19.5 ...
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.ndimage import median_filter

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

PLATE_MM = 8.0  # each side's outer stretch taken as its plate
GUESS_RISE_MM = 0.3
GUESS_RUN_MM = 0.3
WINDOW_MM = (1.5, 0.5)  # plate side, weld side of the guess


def profile_halves(points: np.ndarray, y_mm: float):
    """The profile at ``y_mm`` of a profile scan (``points`` (n, 3) mm, profiles at constant y),
    as two halves ``(side, x, height over its plate's line)``, each ordered from the plate inward."""
    sel = np.abs(points[:, 1] - y_mm) < 1e-3
    if not sel.any():
        raise ValueError(f"no profile at y = {y_mm} mm")
    return split_profile(points[sel, 0], points[sel, 2])


def split_profile(x: np.ndarray, z: np.ndarray):
    """A profile (``x``, ``z`` (n,) mm, any order) as two halves ``(side, x, height over its plate's
    line)``, each ordered from the plate inward."""
    order = np.argsort(x)
    x, z = x[order], z[order]
    top = int(np.argmax(median_filter(z, size=7, mode="nearest")))
    halves = []
    for side, part in (("minus", slice(0, top + 1)), ("plus", slice(top, None))):
        xs, zs = x[part], z[part]
        if side == "plus":
            xs, zs = xs[::-1], zs[::-1]
        outer = np.abs(xs - xs[0]) <= PLATE_MM
        slope, icept = np.polyfit(xs[outer], zs[outer], 1)
        halves.append((side, xs, zs - (slope * xs + icept)))
    return halves


def guess_toe_x(x: np.ndarray, h: np.ndarray) -> float:
    """The first point from the plate inward from which the surface stands ``GUESS_RISE_MM`` over
    it for ``GUESS_RUN_MM`` (mm); ValueError if it never does."""
    start = None
    for i in range(len(x)):
        if h[i] <= GUESS_RISE_MM:
            start = None
        elif start is None:
            start = i
        elif abs(x[i] - x[start]) >= GUESS_RUN_MM:
            return float(x[start])
    raise ValueError(f"the surface never stands {GUESS_RISE_MM} mm over the plate for {GUESS_RUN_MM} mm")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scan", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--y", type=float, nargs="+", required=True, metavar="MM", help="the profiles' y")
    args = parser.parse_args()
    if not args.scan.is_file():
        print(f"draw_mark_sections: no scan at {args.scan}", file=sys.stderr)
        return 2
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MultipleLocator

    from data_catalog.pointclouds import read_point_cloud

    points = read_point_cloud(args.scan, units="mm").points_mm
    args.out.mkdir(parents=True, exist_ok=True)
    for y in args.y:
        fig, axes = plt.subplots(2, 1, figsize=(6.4, 6.4), dpi=90)
        for ax, (side, x, h) in zip(axes, profile_halves(points, y)):
            g = guess_toe_x(x, h)
            sign = 1 if side == "minus" else -1  # x grows from the plate inward on the minus side
            lo, hi = sorted((g - sign * WINDOW_MM[0], g + sign * WINDOW_MM[1]))
            inside = (x >= lo) & (x <= hi)
            ax.plot(x[inside], h[inside], "-", color="0.6", lw=0.6)
            ax.plot(x[inside], h[inside], ".", color="k", ms=2.5)
            ax.set_xlim(lo, hi)
            ax.set_ylim(-0.1, 0.4)
            ax.xaxis.set_major_locator(MultipleLocator(0.2))
            ax.xaxis.set_minor_locator(MultipleLocator(0.05))
            ax.yaxis.set_minor_locator(MultipleLocator(0.05))
            ax.grid(which="major", color="0.75", lw=0.6)
            ax.grid(which="minor", color="0.9", lw=0.4)
            ax.set_title(f"{args.scan.name}  y = {y:g} mm  {side} toe", fontsize=9)
            ax.set_ylabel("height over plate mm", fontsize=8)
            ax.tick_params(labelsize=7)
        axes[1].set_xlabel("x mm (file)", fontsize=8)
        fig.tight_layout()
        fig.savefig(args.out / f"{args.scan.stem}_y{y:05.1f}.png")
        plt.close(fig)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
