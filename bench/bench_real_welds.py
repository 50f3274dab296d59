"""``measure-weld`` on every real scan in a folder (default ``../shared/data/realweld`` beside the
repository), and its consistency without truth: per file and toe side, how many toes are measured
(and why not), the toe position, angle and radius (or "below X") along the weld; the ratio of the
section-to-section scatter to the stated 1-sigma (the scatter of differences between neighbouring
sections over sqrt(2), against the median 1-sigma: near 1 where the weld is uniform, above it
where the weld itself changes); front against back; the same file cut every 0.5 mm (each profile)
and in 1 mm slabs (two profiles together, as an unordered cloud).

    .venv/bin/python bench/bench_real_welds.py [DIR]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from flows.scan_weld import scan_weld_document  # noqa: E402 - after the path is set
from schemas.profile_weld import MeasureWeldConfig  # noqa: E402

DEFAULT_DIR = ROOT.parent / "shared" / "data" / "realweld"
FIGURES = (("toe position", lambda t: t.position_u_mm, lambda t: t.position_sigma_mm),
           ("toe angle", lambda t: t.flank_angle_deg.value, lambda t: t.flank_angle_deg.sigma),
           ("undercut", lambda t: t.undercut_depth_mm.value, lambda t: t.undercut_depth_mm.sigma))


def _ratio(values, sigmas) -> float:
    v, s = np.asarray(values, float), np.asarray(sigmas, float)
    ok = np.isfinite(v) & np.isfinite(s)
    if ok.sum() < 4:
        return float("nan")
    d = np.diff(v[ok])
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2) / np.median(s[ok]))


def describe(doc) -> list[str]:
    rows = []
    for side in ("minus", "plus"):
        toes = [getattr(s.toes, side) for s in doc.geometry.sections]
        extra = [t for t in doc.toes if t.side == side]
        measured = [t for t in toes if t is not None]
        below = [t.toe_radius_below_mm for t in extra if t.toe_radius_below_mm is not None]
        radii = [t.toe_radius_mm.value for t in measured if t.toe_radius_mm.value is not None]
        reasons = sorted({t.reason for t in extra if t.reason})
        cells = [f"{len(measured)}/{len(toes)}"]
        for name, value, sigma in FIGURES:
            v = [value(t) for t in measured]
            s = [sigma(t) for t in measured]
            cells.append(f"{np.median(v):.3f} (sd {np.std(v):.3f}, 1-sigma {np.nanmedian(np.asarray(s, float)):.3f}, "
                         f"ratio {_ratio(v, s):.1f})")
        cells.append(f"{len(radii)} resolved" + (f" (median {np.median(radii):.2f} mm)" if radii else ""))
        cells.append(f"{len(below)} below X, X median {np.median(below):.2f} (min {min(below):.2f}, max {max(below):.2f})"
                     if below else "-")
        cells.append("; ".join(reasons) or "-")
        rows.append(f"| {Path(doc.source.file).name} | {doc.config.step_mm or 'profile'} | {side} | " + " | ".join(cells) + " |")
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folder", nargs="?", type=Path, default=DEFAULT_DIR)
    args = parser.parse_args()
    scans = sorted(args.folder.glob("*.xyz"))
    print("| file | cut | toe | measured | toe position mm median (sd, 1-sigma, ratio) | toe angle deg | undercut mm "
          "| radius resolved | radius below X mm | not measured: why |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for scan in scans:
        for config in (MeasureWeldConfig(), MeasureWeldConfig(step_mm=1.0)):
            t0 = time.perf_counter()
            doc, problems = scan_weld_document(scan, units="mm", line=None, joint="double-sided butt",
                                               treatment="as-welded", config=config)
            for row in describe(doc):
                print(row)
            g = doc.geometry
            h = [s.reinforcement_height_mm.value for s in g.sections if s.reinforcement_height_mm.value is not None]
            w = [s.reinforcement_width_mm.value for s in g.sections if s.reinforcement_width_mm.value is not None]
            print(f"|  | {scan.name}: {len(g.sections)} sections in {time.perf_counter() - t0:.0f} s; height "
                  f"{np.median(h):.3f} mm, width {np.median(w):.2f} mm; verdict {g.summary.verdict} "
                  f"({g.summary.failing} failing, {g.summary.sections_uncertain} uncertain) |||||||||")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
