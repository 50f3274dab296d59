"""A butt weld found in a scan's points and cut into sections (``tasks.profile_weld`` measures each):
a patch of one weld from any profile scanner, no frame, no manifest.

Frame: ``n`` the plates' normal (the points' direction of least spread, turned toward the file's
+z: a profile scanner's height; a patch must therefore reach further along the weld than the
weld is high), ``t`` along the weld, ``a = n x t`` across it. A section's
profile is ``u`` (along ``a``, mm from the weld line) and ``h`` (along ``n``, mm from it).

- The weld line, when none is given: the direction in the plates' plane along which the surface
  changes least (the least variance of heights within 0.5 mm strips along it, searched every
  1 deg, then 0.1 deg), and across it the middle of the band that rises over half the highest rise
  above the line through the scan's two edges (the median heights of its outer ``_EDGE_MM``).
  A rise below ``min_rise_mm``: no weld in the scan.
- Sections: a profile scan (points in lines across the weld, each line at one value of a file
  axis: at most one distinct value per 50 points) is cut one section per profile: each profile,
  projected on ``a`` and ``n``, is a section (a prismatic weld's section is the same seen
  obliquely). An unordered cloud is cut in slabs: the points within ``half_width_mm`` of planes
  across the line every ``step_mm``, projected on ``a`` and ``n`` together.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from tasks.profile_weld import ProfileResult, ProfileSettings, measure_profile

__all__ = ["WeldLine", "ScanMeasurement", "check_scan_scale", "find_weld_line", "given_weld_line", "measure_scan"]

_EDGE_MM = 2.0  # the scan's edges across the weld: the plates' first heights
_BIN_MM = 0.5  # strips along the weld for its direction and height profile
MIN_SCAN_EXTENT_MM = 2.0  # a scanned weld spans more than this (a smaller scan: its unit is wrong)
_TYPICAL_EXTENT_MM = 30.0  # what a weld scan spans, for how far off a too small one is


@dataclass(frozen=True)
class WeldLine:
    """A straight weld line on the scan (its frame, mm) and the frame around it."""

    start_mm: tuple[float, float, float]
    end_mm: tuple[float, float, float]
    normal: tuple[float, float, float]  # the plates' normal, heights along it
    across: tuple[float, float, float]
    found: str  # "given" | "auto"


@dataclass(frozen=True)
class ScanMeasurement:
    line: WeldLine
    sections: list[ProfileResult]
    profile_scan: bool  # each profile a section (else slabs of an unordered cloud)
    profile_pitch_mm: float | None  # between profiles along the weld (profile scans)


def check_scan_scale(points: np.ndarray) -> None:
    """Refuse a scan too small to hold a weld (``points`` (n, 3) mm): metres read as millimetres."""
    points = _checked(points)
    extent = float(np.ptp(points, axis=0).max())
    if extent < MIN_SCAN_EXTENT_MM:
        factor = 10 ** round(math.log10(_TYPICAL_EXTENT_MM / max(extent, 1e-12)))
        raise ValueError(f"the scan spans only {extent:.4g} mm (a weld scan spans tens of mm): a part about "
                         f"{factor:,} times too small; are its coordinates metres read as millimetres? "
                         "(give its unit: --units m)")


def _checked(points: np.ndarray) -> np.ndarray:
    points = np.asarray(points, np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 10 or not np.isfinite(points).all():
        raise ValueError(f"points must be a finite (n >= 10, 3) array, mm; got {points.shape}")
    return points


def _plane(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(mean, normal, in-plane axes (2, 3)) of the points: the normal their least spread, toward +z."""
    mean = points.mean(axis=0)
    _, vectors = np.linalg.eigh(np.cov((points - mean).T))
    n = vectors[:, 0] if vectors[2, 0] >= 0 else -vectors[:, 0]
    return mean, n, vectors[:, 1:].T


def _strip_spread(u: np.ndarray, h: np.ndarray) -> float:
    """Summed variance of heights within 0.5 mm strips of u."""
    b = np.floor((u - u.min()) / _BIN_MM).astype(np.int64)
    n = np.bincount(b)
    s = np.bincount(b, h)
    return float((h * h).sum() - (s[n > 0] ** 2 / n[n > 0]).sum())


def find_weld_line(points: np.ndarray, *, min_rise_mm: float) -> WeldLine:
    """The weld line on the data: along the least change of height, through the raised band's
    middle. ``points`` (n, 3) mm. ValueError: no weld (a rise below ``min_rise_mm``)."""
    points = _checked(points)
    check_scan_scale(points)
    mean, n, (e1, e2) = _plane(points)
    P = points - mean
    h = P @ n
    x1, x2 = P @ e1, P @ e2

    def spread(deg: float) -> float:
        r = math.radians(deg)
        return _strip_spread(math.cos(r) * x1 + math.sin(r) * x2, h)

    coarse = min(np.arange(0.0, 180.0, 1.0), key=spread)
    best = min(np.arange(coarse - 1.0, coarse + 1.0001, 0.1), key=spread)
    r = math.radians(best)
    a = math.cos(r) * e1 + math.sin(r) * e2
    if a @ np.array([1.0, 0.0, 0.0]) < 0 or (abs(a[0]) < 1e-9 and a[1] < 0):  # across: toward +x
        a = -a
    t = np.cross(n, a)
    u, s = P @ a, P @ t
    bins = np.floor((u - u.min()) / _BIN_MM).astype(np.int64)
    centres = u.min() + (np.arange(bins.max() + 1) + 0.5) * _BIN_MM
    heights = np.array([np.median(h[bins == k]) if np.any(bins == k) else np.nan for k in range(bins.max() + 1)])
    ok = np.isfinite(heights)
    centres, heights = centres[ok], heights[ok]
    lo_edge, hi_edge = centres < centres.min() + _EDGE_MM, centres > centres.max() - _EDGE_MM
    h0, h1 = float(np.median(heights[lo_edge])), float(np.median(heights[hi_edge]))
    u0, u1 = float(centres[lo_edge].mean()), float(centres[hi_edge].mean())
    rise = heights - (h0 + (h1 - h0) * (centres - u0) / max(u1 - u0, 1e-9))
    top = int(np.argmax(rise))
    if rise[top] < min_rise_mm:
        raise ValueError(f"no weld in the scan: its surface rises at most {rise[top]:.3f} mm over the line between "
                         f"its edges across the likeliest weld direction (a weld cap rises at least {min_rise_mm:g} mm)")
    high = rise > 0.5 * rise[top]
    lo = hi = top
    while lo > 0 and high[lo - 1]:
        lo -= 1
    while hi < len(high) - 1 and high[hi + 1]:
        hi += 1
    uc = 0.5 * (centres[lo] + centres[hi])
    base = h0 + (h1 - h0) * (uc - u0) / max(u1 - u0, 1e-9)
    origin = mean + uc * a + base * n
    start, end = origin + s.min() * t, origin + s.max() * t
    return WeldLine(tuple(map(float, start)), tuple(map(float, end)), tuple(map(float, n)), tuple(map(float, a)), "auto")


def given_weld_line(points: np.ndarray, start_mm, end_mm) -> WeldLine:
    """The weld line given (two points, mm) in the scan's frame; ValueError when no point of the
    scan lies within 1 mm of it (along the plates' plane)."""
    points = _checked(points)
    check_scan_scale(points)
    p0, p1 = np.asarray(start_mm, np.float64), np.asarray(end_mm, np.float64)
    length = float(np.linalg.norm(p1 - p0))
    if p0.shape != (3,) or p1.shape != (3,) or length == 0:
        raise ValueError(f"a weld line is two different points x,y,z; got {list(start_mm)} and {list(end_mm)}")
    t = (p1 - p0) / length
    _, n, _ = _plane(points)
    n = n - (n @ t) * t
    n = n / np.linalg.norm(n)
    a = np.cross(n, t)
    P = points - p0
    s, u = P @ t, P @ a
    under = np.count_nonzero((s >= 0) & (s <= length) & (np.abs(u) <= 1.0))
    if under < 10:
        lo, hi = points.min(axis=0), points.max(axis=0)
        raise ValueError(f"the weld line {_xyz(p0)}:{_xyz(p1)} lies outside the scan ({under} points within 1 mm of it; "
                         f"the scan spans x {lo[0]:.2f}..{hi[0]:.2f}, y {lo[1]:.2f}..{hi[1]:.2f}, "
                         f"z {lo[2]:.2f}..{hi[2]:.2f} mm)")
    return WeldLine(tuple(map(float, p0)), tuple(map(float, p1)), tuple(map(float, n)), tuple(map(float, a)), "given")


def _xyz(p: np.ndarray) -> str:
    return ",".join(f"{v:g}" for v in p)


def _profiles(points: np.ndarray) -> np.ndarray | None:
    """Each point's profile (an index), where the scan is one of profiles: lines at distinct values
    of one file axis, at most one value per 50 points (and at least 3 of them); else None."""
    for k in (1, 0, 2):
        values, index = np.unique(np.round(points[:, k], 4), return_inverse=True)
        if 3 <= len(values) <= len(points) / 50:
            return index
    return None


def _section_frame(origin: np.ndarray, t: np.ndarray, a: np.ndarray, n: np.ndarray, pos: float):
    """``to_frame(u, h)`` of the section ``pos`` along the line: the scan-frame point of a profile
    position (``t`` along the line, ``a`` across, ``n`` the plates' normal)."""
    def to_frame(uu, hh):
        return origin + pos * t + uu * a + hh * n
    return to_frame


_NEIGHBOURS = 3  # sections either side a toe is held against
_OFF_MM = 0.25  # a toe further than this (or 4 of its and its neighbours' sigmas) from theirs is fitted again
_STARTS_MM = (0.0, -0.05, 0.05, -0.1, 0.1, -0.15, 0.15, -0.2, 0.2)  # ... started this far from their toe


def _along_the_weld(sections: list, groups: list, u: np.ndarray, h: np.ndarray, *, settings: ProfileSettings,
                    treated: bool, name: str, frame) -> list:
    """Each toe held against its neighbours along the weld: one further from the median of the
    ``_NEIGHBOURS`` sections either side than ``_OFF_MM`` and 4 combined sigmas (its own, their
    spread's) is fitted again from their toe (a dip in the plate beside a toe reads as flank, and
    the fit then lands half a millimetre out). The section measured again is kept when each toe
    fitted again lands among its neighbours (its note says so), else the first stays."""
    origin, t, a, n = frame
    position = np.array([[r.toes[k].fit.position_u_mm if r.toes[k].fit is not None else np.nan for k in (0, 1)]
                         for r in sections]).reshape(-1, 2)
    out = list(sections)
    for i, r in enumerate(sections):
        off: dict[str, tuple[float, float, float]] = {}  # side -> (neighbours' median, limit, first fit's position)
        for k, side in enumerate(("minus", "plus")):
            fit = r.toes[k].fit
            if fit is None or fit.groove is not None:
                continue
            near = np.r_[position[max(i - _NEIGHBOURS, 0):i, k], position[i + 1:i + 1 + _NEIGHBOURS, k]]
            near = near[np.isfinite(near)]
            if len(near) < 3:
                continue
            median = float(np.median(near))
            spread = 1.4826 * float(np.median(np.abs(near - median)))
            sigma = fit.position_sigma_mm if math.isfinite(fit.position_sigma_mm) else 0.0
            limit = max(_OFF_MM, 4 * math.hypot(sigma, spread))
            if abs(fit.position_u_mm - median) > limit:
                off[side] = (median, limit, fit.position_u_mm)
        if not off:
            continue
        pos, sel = groups[i]
        to_frame = _section_frame(origin, t, a, n, pos)
        best = None
        for shift in _STARTS_MM:  # started at and around their toe: the best fit that lands among them
            again = measure_profile(u[sel], h[sel], settings=settings, treated=treated, line=name, position_mm=pos,
                                    to_frame=to_frame, toe_guess_u={side: m + shift for side, (m, _, _) in off.items()})
            fits = {side: again.toes[k].fit for k, side in enumerate(("minus", "plus")) if side in off}
            if all(f is not None and abs(f.position_u_mm - off[side][0]) <= off[side][1] for side, f in fits.items()):
                rms = sum(f.rms_mm ** 2 for f in fits.values())
                if best is None or rms < best[0]:
                    best = (rms, again)
        if best is None:
            continue
        again = best[1]
        toes = list(again.toes)
        for k, side in enumerate(("minus", "plus")):
            if side in off:
                median, _, first = off[side]
                note = (f"fitted again from its neighbours' toe ({median:.3f} mm): the first fit lay {first - median:+.3f} "
                        "mm off")
                toes[k] = replace(toes[k], fit=replace(toes[k].fit, note="; ".join(x for x in (toes[k].fit.note, note) if x)))
        out[i] = replace(again, toes=tuple(toes), section=replace(again.section, toes=tuple(tr.fit for tr in toes)))
    return out


def measure_scan(points: np.ndarray, line: WeldLine, *, settings: ProfileSettings, treated: bool,
                 step_mm: float | None, half_width_mm: float | None, name: str) -> ScanMeasurement:
    """The weld's sections along ``line``: one per profile of a profile scan (``step_mm`` None),
    else slabs ``2 half_width_mm`` thick every ``step_mm`` (the half width defaulting to half the
    step). ValueError when every section lacks its plate on one side of the weld (the scan holds no
    points there)."""
    points = _checked(points)
    origin = np.asarray(line.start_mm)
    t = np.asarray(line.end_mm) - origin
    length = float(np.linalg.norm(t))
    t = t / length
    n, a = np.asarray(line.normal), np.asarray(line.across)
    P = points - origin
    s, u, h = P @ t, P @ a, P @ n
    profile = _profiles(points) if step_mm is None else None
    groups: list[tuple[float, np.ndarray]] = []
    pitch = None
    if profile is not None:
        for k in range(profile.max() + 1):
            sel = profile == k
            pos = float(np.mean(s[sel]))
            if -0.5 <= pos <= length + 0.5:
                groups.append((pos, sel))
        positions = np.array([g[0] for g in groups])
        pitch = float(np.median(np.diff(np.sort(positions)))) if len(positions) > 1 else None
    else:
        step = step_mm if step_mm is not None else 1.0
        half = half_width_mm if half_width_mm is not None else step / 2
        for pos in np.arange(max(s.min(), 0.0) + half, min(s.max(), length) - half + 1e-9, step):
            groups.append((float(pos), np.abs(s - pos) <= half))
    sections = []
    for pos, sel in groups:
        sections.append(measure_profile(u[sel], h[sel], settings=settings, treated=treated, line=name, position_mm=pos,
                                        to_frame=_section_frame(origin, t, a, n, pos)))
    sections = _along_the_weld(sections, groups, u, h, settings=settings, treated=treated, name=name,
                               frame=(origin, t, a, n))
    for side, k in (("minus", 0), ("plus", 1)):
        missing = [r.toes[k].reason for r in sections if r.toes[k].plate_missing]
        if sections and len(missing) == len(sections):
            raise ValueError(f"no plate on the {side} side of the weld ({'-' if k == 0 else '+'}across) in any of its "
                             f"{len(sections)} sections: the scan must reach past both toes onto the plates "
                             f"(first section: {missing[0]})")
    return ScanMeasurement(line, sections, profile is not None, pitch)
