"""The weld measured on the reconstruction: sections across each weld line, a fit per toe.

A weld line is a polyline on one face of the part (specimen frame, mm). Its section frame:
``t`` along the line, ``n`` the face's outward normal (the axis the measured normals near the line
lie along, turned the way the nearest ones look),
``a`` across the weld (``n x t``, turned to the specimen's +x where it has a component there).
Each section takes the measured points within ``section_half_width_mm`` of its position along the
line and reads them as a profile: ``u`` across (mm, along ``a``), ``h`` height (mm, along ``n``).

Per section (every figure a value and its 1-sigma):

- the two plates: a line each (``tasks.weld_fits.fit_plate_line``: under any sticker or spatter)
  on ``plate_window_mm`` beside the weld's centre; axial misalignment (the plus plate's height over the minus one's at the
  centre, along ``n``) and angular misalignment (the plus plate's slope less the minus one's);
- each toe (``minus``: u < centre, ``plus``: u > centre): ``tasks.weld_fits.fit_toe`` as welded,
  ``fit_groove`` where a treated toe dips below the plate;
- reinforcement height (the peak over the line between the toes on their plates, a parabola over
  the peak, on the points within ``height_half_width_mm`` of the section, or its nearest ten over
  the cap's middle) and width (between the toes).

The line is refined on the data: a first pass finds each section's centre (a treated weld's: the
midpoint of its grooves' centres, steadier than its toes, which wander with the grooves' widths),
a line through them (robust) gives the weld's true offset and direction in the face, and the
sections are cut again across it.
"""

from __future__ import annotations

import concurrent.futures
import math
from dataclasses import dataclass, field

import numpy as np

from tasks.weld_fits import (TOE_RADIUS_BOUNDS_MM, Measured, SectionSettings, ToeFit, fit_groove, fit_plate_line,
                             fit_robust_line, fit_toe, propagate)

__all__ = ["SectionMeasurement", "WeldLineMeasurement", "measure_section", "measure_weld_line",
           "along_weld_statistics", "toe_polylines", "peak_rise", "TOE_SIDES"]

TOE_SIDES = ("minus", "plus")
_NAN = float("nan")


@dataclass(frozen=True)
class SectionMeasurement:
    line: str
    position_mm: float  # along the line from its first point
    centre_mm: tuple[float, float, float]  # the weld's centre at the section, the frame the points came in
    height: Measured
    width: Measured
    axial_misalignment: Measured
    angular_misalignment_deg: Measured
    toes: tuple[ToeFit | None, ToeFit | None]
    n_points: int
    note: str = ""
    # where the line is refined through (the points' frame): a treated weld's grooves' centres'
    # midpoint (the toes where the grooves meet the weld wander with the grooves' widths, ~1 mm;
    # the grooves' centres ~0.2 mm); None: centre_mm
    axis_mm: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class WeldLineMeasurement:
    line: str
    sections: list[SectionMeasurement]
    offset_mm: float  # the refined line's shift across the nominal one (along a), at its middle
    turn_deg: float  # the refined line's turn from the nominal one, in the face
    normal: tuple[float, float, float]
    across: tuple[float, float, float]
    extent_mm: tuple[float, float] = field(default=(0.0, 0.0))  # the measured part of the line


def _centre_guess(u: np.ndarray, h: np.ndarray) -> float | None:
    """The weld's centre across a profile: the middle of the band raised over the plate (median
    height), over half the highest rise (on 0.5 mm bins)."""
    if len(u) < 10:
        return None
    plate = fit_robust_line(u, h, min_points=10)  # the plates dominate a section: tilt taken out
    base = plate.at(u) if plate is not None else np.median(h)
    bins = np.floor(u / 0.5).astype(np.int64)
    ub, inv = np.unique(bins, return_inverse=True)
    top = np.full(len(ub), -np.inf)
    np.maximum.at(top, inv, h - base)
    if top.max() <= 0:
        return None
    high = top > 0.5 * top.max()
    lo = hi = int(np.argmax(top))  # the run of high bins around the highest (gaps of 2 bins bridged)
    while lo > 0 and (high[lo - 1] or (lo > 1 and high[lo - 2] and ub[lo - 1] - ub[lo - 2] <= 2)):
        lo -= 1
    while hi < len(ub) - 1 and (high[hi + 1] or (hi < len(ub) - 2 and high[hi + 2] and ub[hi + 2] - ub[hi + 1] <= 2)):
        hi += 1
    return float((ub[lo] + ub[hi] + 1) * 0.25)


MAX_TOE_SIGMA_MM = 1.0  # a toe placed no better than this is not a toe (the ci preset's 0.3 mm points: 0.19 at most)


def _not_a_toe(fit: ToeFit, settings: SectionSettings) -> str | None:
    """Why a toe fit (``v`` outward from the weld's centre) is no evidence of a weld toe, or None:
    its position not determined (1-sigma over MAX_TOE_SIGMA_MM, or not finite), its fillet run to
    the fit's ceiling (a plate's edge or a sticker's, not a fillet), or the toe out where the
    plates are fitted (``plate_window_mm[0]`` from the centre: then the "plate" held the weld)."""
    sd = fit.position_sigma_mm
    if not math.isfinite(sd) or sd > MAX_TOE_SIGMA_MM:
        return f"places it to {sd:.3g} mm (1-sigma; a toe is placed within {MAX_TOE_SIGMA_MM:g} mm)"
    if fit.groove is None and fit.notch_radius.value >= TOE_RADIUS_BOUNDS_MM[1] * 0.999:
        return f"ran to its largest fillet radius ({TOE_RADIUS_BOUNDS_MM[1]:g} mm): no toe between flank and plate"
    if fit.position_u_mm > settings.plate_window_mm[0]:
        return (f"lies {fit.position_u_mm:.2f} mm from the weld's centre, beyond where the plates are fitted "
                f"({settings.plate_window_mm[0]:g} mm)")
    return None


def measure_section(u: np.ndarray, h: np.ndarray, s: np.ndarray, *, settings: SectionSettings, treated: bool,
                    line: str, position_mm: float, to_frame) -> SectionMeasurement:
    """One section: ``u`` across (mm), ``h`` along the face normal (mm), ``s`` along the line
    relative to the section (mm), (n,) float64 each. ``treated``: look for HFMI grooves.
    ``to_frame(u, h)``: the 3-D point (the points' frame) of a profile position."""
    n = len(u)
    empty = (None, None)

    def failed(why: str) -> SectionMeasurement:
        none = Measured.none()
        return SectionMeasurement(line, position_mm, tuple(float(x) for x in to_frame(0.0, 0.0)), none, none, none,
                                  none, empty, n, why)

    c = _centre_guess(u, h)
    if c is None:
        return failed("no raised weld in the section")
    near, far = settings.plate_window_mm
    plates = []
    for sign in (-1, 1):
        sel = (sign * (u - c) > near) & (sign * (u - c) < far)
        plates.append(fit_plate_line(u[sel], h[sel], min_points=settings.min_points))
    if plates[0] is None or plates[1] is None:
        return failed("a plate beside the weld has too few points")
    toes: list[ToeFit | None] = []
    for side, sign, plate in (("minus", -1, plates[0]), ("plus", 1, plates[1])):
        half = sign * (u - c) >= 0
        v = sign * (u[half] - c)
        rel = h[half] - plate.at(u[half])
        order = np.argsort(v)
        v, rel = v[order], rel[order]
        raised = rel > settings.toe_threshold_mm
        if not raised.any():
            toes.append(None)
            continue
        # outward from the centre, the last point of the raised run that starts at the centre
        first_low = np.flatnonzero(~raised & (v > v[raised].min()))
        guess = float(v[first_low[0]]) if len(first_low) else float(v[raised].max())
        fit = fit_groove(v, rel, settings=settings, side=side, toe_guess_v=guess) if treated else None
        if fit is None:
            fit = fit_toe(v, rel, settings=settings, side=side, toe_guess_v=guess)
        if fit is not None:
            why = _not_a_toe(fit, settings)
            if why is not None:
                return failed(f"no weld found at the line here: the {side} toe's fit {why}")
            fit = ToeFit(**{**fit.__dict__, "position_u_mm": c + sign * fit.position_u_mm})
        toes.append(fit)
    # misalignment at the weld's centre
    a, b = plates
    axial = b.at(c) - a.at(c)
    J = np.array([c, 1.0])
    axial_sd = math.sqrt(max(J @ a.cov @ J + J @ b.cov @ J, 0.0))
    ang = math.degrees(math.atan(b.slope) - math.atan(a.slope))
    ang_sd = math.degrees(math.sqrt(max(a.cov[0, 0] / (1 + a.slope ** 2) ** 2 + b.cov[0, 0] / (1 + b.slope ** 2) ** 2, 0)))
    height = width = Measured.none()
    centre = c
    if toes[0] is not None and toes[1] is not None:
        u0, u1 = toes[0].position_u_mm, toes[1].position_u_mm
        width = Measured(u1 - u0, math.hypot(toes[0].position_sigma_mm, toes[1].position_sigma_mm))
        centre = (u0 + u1) / 2
        z0, z1 = float(a.at(u0)), float(b.at(u1))
        # the peak on the points nearest the section along the line (bead ripples): within
        # height_half_width_mm, or out to the tenth nearest point over the cap's middle
        # (at least the middle millimetre: a very shallow groove's wide circle can cut the cap
        # nearly to its top, the toes where it meets the weld a fraction of a millimetre apart)
        between = (u > min(u0, centre - 0.5)) & (u < max(u1, centre + 0.5))
        middle = np.sort(np.abs(s[between & (np.abs(u - centre) < 2.0)]))
        reach = max(settings.height_half_width_mm, float(middle[min(9, len(middle) - 1)]) if len(middle) else np.inf)
        between &= np.abs(s) <= reach
        rise = h[between] - (z0 + (z1 - z0) * (u[between] - u0) / max(u1 - u0, 1e-9))
        height = peak_rise(u[between], rise)
        if math.isfinite(height.value) and height.value < settings.min_height_mm:
            return failed(f"no weld found at the line here: the cap rises {height.value:.3f} mm over its plates, "
                          f"less than {settings.min_height_mm:g} mm (a sticker's paper, the plates' waviness)")
    axis = None
    if toes[0] is not None and toes[1] is not None and toes[0].groove is not None and toes[1].groove is not None:
        mid = c + (toes[1].groove.centre_v_mm - toes[0].groove.centre_v_mm) / 2
        axis = tuple(float(x) for x in to_frame(mid, float(a.at(mid))))
    return SectionMeasurement(line, position_mm, tuple(float(x) for x in to_frame(centre, float(a.at(centre)))),
                              height, width, Measured(float(axial), axial_sd), Measured(ang, ang_sd),
                              (toes[0], toes[1]), n, axis_mm=axis)


def peak_rise(u: np.ndarray, rise: np.ndarray) -> Measured:
    """The highest rise: a parabola over the points within 1 mm of the highest one."""
    if len(u) < 3:
        return Measured.none()
    k = int(np.argmax(rise))
    sel = np.abs(u - u[k]) <= 1.0
    if sel.sum() < 4:
        return Measured(float(rise[k]), _NAN)
    x = u[sel] - u[k]
    A = np.stack([x * x, x, np.ones(len(x))], 1)
    coef, *_ = np.linalg.lstsq(A, rise[sel], rcond=None)
    r = rise[sel] - A @ coef
    cov = np.linalg.pinv(A.T @ A) * float(r @ r) / max(len(r) - 3, 1)

    def top(c):
        if c[0] >= -1e-9:  # not a cap: the highest fitted value on the points
            return float(np.max(c[0] * x * x + c[1] * x + c[2]))
        xm = float(np.clip(-c[1] / (2 * c[0]), x.min(), x.max()))
        return c[0] * xm * xm + c[1] * xm + c[2]

    return Measured(float(top(coef)), propagate(top, coef, cov))


# how far from the line the points decide which way its face looks (the cap and the plate beside it,
# not the part's far face: 3 mm is under any plate a section is read on)
_FACE_SIDE_MM = 3.0


def _frame(points_line: np.ndarray, normals_near: np.ndarray,
           distance_near: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The line's frame (t along, n its face's outward normal, a across) from the normals of the
    points near it (``distance_near`` their distances from the line). ``n``: the axis the normals
    lie along most, across the line (the largest eigenvector of their second moment; the side
    walls' normals, along the line, drop out), turned the way the normals nearest the line look.
    Not their mean: within reach of a line on one face lie both faces of a plate thinner than the
    reach, whose normals cancel (the paper preset's 20 mm plate, 32 mm reach: a mean of 0.005,
    read as a face tilted 26 deg)."""
    t = points_line[-1] - points_line[0]
    t = t / np.linalg.norm(t)
    across = normals_near - np.outer(normals_near @ t, t)
    _, vectors = np.linalg.eigh(across.T @ across)
    n = vectors[:, -1]
    weight = np.exp(-0.5 * (np.asarray(distance_near) / _FACE_SIDE_MM) ** 2)
    if float(((across @ n) * weight).sum()) < 0:
        n = -n
    n = n - (n @ t) * t
    n = n / np.linalg.norm(n)
    a = np.cross(n, t)
    if a[0] < 0 or (abs(a[0]) < 1e-9 and a[1] < 0):
        a = -a
    return t, n, a


def measure_weld_line(points: np.ndarray, normals: np.ndarray, line_points_mm: np.ndarray, *, name: str,
                      step_mm: float, section_half_width_mm: float, reach_mm: float, end_margin_mm: float,
                      min_normal_cos: float, settings: SectionSettings, treated: bool,
                      workers: int = 1) -> WeldLineMeasurement:
    """Sections every ``step_mm`` across one weld line. ``points``, ``normals``: (n, 3) float64, mm,
    unit, the measured surface in the frame of ``line_points_mm`` ((k, 3), a straight line: its
    first and last point), normals outward. Points within ``reach_mm`` across the line, facing
    its face (normal . n > ``min_normal_cos``) are read; sections run where they reach, less
    ``end_margin_mm`` at each end. ``workers``: sections measured at once on that many threads
    (numpy's partitions and arithmetic release the GIL; each section's fit is its own, so the
    result does not depend on it)."""
    points = np.asarray(points, np.float64)
    normals = np.asarray(normals, np.float64)
    line = np.asarray(line_points_mm, np.float64)
    if points.ndim != 2 or points.shape[1:] != (3,) or normals.shape != points.shape:
        raise ValueError(f"points and normals must be (n, 3) arrays of one shape, got {points.shape} and {normals.shape}")
    if line.ndim != 2 or line.shape[1:] != (3,) or len(line) < 2:
        raise ValueError(f"line_points_mm must be (k >= 2, 3), got {line.shape}")
    if step_mm <= 0 or section_half_width_mm <= 0:
        raise ValueError(f"step_mm and section_half_width_mm must be positive, got {step_mm}, {section_half_width_mm}")
    t = line[-1] - line[0]
    length = float(np.linalg.norm(t))
    t = t / length
    rel = points - line[0]
    s_all = rel @ t
    across = rel - np.outer(s_all, t)
    near = (np.linalg.norm(across, axis=1) < reach_mm) & (s_all > -1) & (s_all < length + 1)
    if near.sum() < settings.min_points:
        return WeldLineMeasurement(name, [], 0.0, 0.0, (0.0, 0.0, 1.0), (1.0, 0.0, 0.0))
    t, n, a = _frame(line, normals[near], np.linalg.norm(across[near], axis=1))
    face = near & (normals @ n > min_normal_cos) & (np.abs(rel @ n) < reach_mm / 2)
    P = rel[face]
    s, u, h = P @ t, P @ a, P @ n
    origin = line[0]
    if len(s) < settings.min_points:
        return WeldLineMeasurement(name, [], 0.0, 0.0, tuple(float(x) for x in n), tuple(float(x) for x in a))

    def cut(s, u, h, origin, t, a, n):
        lo, hi = float(s.min()) + end_margin_mm, float(s.max()) - end_margin_mm
        order = np.argsort(s)
        s, u, h = s[order], u[order], h[order]
        if hi < lo:
            return []

        def one(pos):
            i0, i1 = np.searchsorted(s, [pos - section_half_width_mm, pos + section_half_width_mm])

            def to_frame(uu, hh):
                return origin + pos * t + uu * a + hh * n

            try:
                return measure_section(u[i0:i1], h[i0:i1], s[i0:i1] - pos, settings=settings, treated=treated,
                                       line=name, position_mm=float(pos), to_frame=to_frame)
            except (ValueError, np.linalg.LinAlgError) as exc:  # one section's fit, not the weld's
                none = Measured.none()
                return SectionMeasurement(name, float(pos), tuple(float(x) for x in to_frame(0.0, 0.0)), none,
                                          none, none, none, (None, None), int(i1 - i0), f"fit failed: {exc}")

        positions = np.arange(np.ceil(lo / step_mm) * step_mm, hi + 1e-9, step_mm)
        if workers <= 1 or len(positions) < 2:
            return [one(pos) for pos in positions]
        with concurrent.futures.ThreadPoolExecutor(workers, thread_name_prefix="sections") as pool:
            return list(pool.map(one, positions))  # in the positions' order, each its own (no shared state)

    first = cut(s, u, h, origin, t, a, n)
    # the line refined on the data: a robust line through the sections' centres, in the face
    cs = np.array([[sec.position_mm, (np.asarray(sec.axis_mm if sec.axis_mm is not None else sec.centre_mm) - origin) @ a]
                   for sec in first if sec.width.value == sec.width.value])
    offset = turn = 0.0
    sections = first
    if len(cs) >= 3:
        fit = fit_robust_line(cs[:, 0], cs[:, 1], min_points=3)  # centres off on either side
        if fit is not None:
            turn = math.atan(fit.slope)
            origin = origin + fit.intercept * a
            t2 = math.cos(turn) * t + math.sin(turn) * a
            a2 = np.cross(n, t2)
            a2 = a2 if a2 @ a > 0 else -a2
            t, a = t2, a2
            P = points[face] - origin
            s, u, h = P @ t, P @ a, P @ n
            sections = cut(s, u, h, origin, t, a, n)
            offset = fit.intercept + fit.slope * length / 2
    extent = (float(s.min()), float(s.max())) if len(s) else (0.0, 0.0)
    return WeldLineMeasurement(name, sections, float(offset), math.degrees(turn), tuple(float(x) for x in n),
                               tuple(float(x) for x in a), extent)


def along_weld_statistics(values: np.ndarray, positions: list) -> dict:
    """min, 5th / 50th / 95th percentile and max of one figure along the weld, and where its lowest
    and highest are (``positions``: one label per value). NaN values are not counted."""
    values = np.asarray(values, np.float64)
    ok = np.isfinite(values)
    if not ok.any():
        return {"n": 0}
    v = values[ok]
    where = [p for p, k in zip(positions, ok) if k]
    return {"n": int(ok.sum()), "min": round(float(v.min()), 4), "p5": round(float(np.percentile(v, 5)), 4),
            "median": round(float(np.median(v)), 4), "p95": round(float(np.percentile(v, 95)), 4),
            "max": round(float(v.max()), 4), "min_at": where[int(np.argmin(v))], "max_at": where[int(np.argmax(v))]}


def toe_polylines(lines: list[WeldLineMeasurement]) -> list[tuple[str, str, np.ndarray, np.ndarray]]:
    """The measured weld toes as polylines, one per weld line and side, in the frame the points
    came in, mm: (line, side, positions along the line (k,), toe points (k, 3)), sorted by line
    and side; each section's toe on its line's across direction from the section's centre (where
    both toes were fitted: the centre is midway between them). Lines with fewer than two such
    sections give none."""
    found: dict[tuple[str, str], list[tuple[float, np.ndarray]]] = {}
    for line in lines:
        across = np.asarray(line.across, np.float64)
        for sec in line.sections:
            if sec.toes[0] is None or sec.toes[1] is None:
                continue
            centre_u = (sec.toes[0].position_u_mm + sec.toes[1].position_u_mm) / 2
            for side, toe in zip(TOE_SIDES, sec.toes):
                point = np.asarray(sec.centre_mm, np.float64) + (toe.position_u_mm - centre_u) * across
                found.setdefault((sec.line, side), []).append((sec.position_mm, point))
    out = []
    for (name, side), rows in sorted(found.items()):
        if len(rows) < 2:
            continue
        rows.sort(key=lambda r: r[0])
        out.append((name, side, np.array([p for p, _ in rows], np.float64), np.array([q for _, q in rows], np.float64)))
    return out
