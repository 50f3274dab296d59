"""The weld as the QA page draws it, from the weld document (``schemas.weld_document``): which
cross-sections to draw (the failing first), each drawn section's measured points in its plane
with its toes and the drawing's plate face, and each figure's values along the weld with its
acceptance limits. Specimen frame, mm and degrees; the pictures are ``tasks.report_figures``'s
``weld_section`` and ``along_weld``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from schemas.acceptance import AcceptanceRule
from schemas.weld_document import Figure, FilletWeldSection, WeldGeometry, WeldLineFound, WeldSection
from tasks.arrays import distinct
from tasks.report_figures import AlongWeldSeries

__all__ = ["TOE_SERIES", "SECTION_SERIES", "FILLET_SERIES", "figure_value", "along_weld_series", "chosen_sections", "SectionCut",
           "section_cut", "ToeCloseup", "toe_closeups", "near_sections", "CLOSEUP_REACH_MM"]

CLOSEUP_REACH_MM = 2.5  # a toe's close-up: its points this far along its plate and over it

# the figures drawn along the weld: (name in the document, label, unit)
TOE_SERIES = (("toe_radius_mm", "toe radius", "mm"), ("flank_angle_deg", "flank angle", "deg"),
              ("undercut_depth_mm", "undercut", "mm"), ("groove_depth_mm", "groove depth", "mm"),
              ("groove_width_mm", "groove width", "mm"))
SECTION_SERIES = (("reinforcement_height_mm", "height", "mm"),
                  ("reinforcement_width_mm", "width", "mm"),
                  ("axial_misalignment_mm", "axial misal.", "mm"),
                  ("angular_misalignment_deg", "angular misal.", "deg"))
FILLET_SERIES = (("leg_base_mm", "leg on the base", "mm"), ("leg_stem_mm", "leg on the stem", "mm"),
                 ("throat_mm", "throat", "mm"), ("convexity_mm", "convexity", "mm"))


def figure_value(m: Figure | None) -> tuple[float, float]:
    """A figure's (value, 1-sigma), NaN where not determined."""
    if m is None or m.value is None:
        return math.nan, math.nan
    return float(m.value), math.nan if m.sigma is None else float(m.sigma)


def _limits(rule: AcceptanceRule | None, figure: str) -> tuple[float | None, float | None]:
    limits = None if rule is None else rule.limits(figure)
    return (None, None) if limits is None else (limits.min, limits.max)


def _curve(rows: list[tuple[float, float, float, bool]]):
    """(position, value, sigma, failing) rows -> four (n,) arrays: float, float, float, bool."""
    arr = np.array(rows, dtype=object)
    return arr[:, 0].astype(float), arr[:, 1].astype(float), arr[:, 2].astype(float), arr[:, 3].astype(bool)


def along_weld_series(geometry: WeldGeometry) -> list[AlongWeldSeries]:
    """Each figure along each weld line: per toe (``TOE_SERIES``; the groove's on a treated weld
    only; a toe never measured left out) and per section (``SECTION_SERIES``, a fillet weld's
    ``FILLET_SERIES``), in that order, with the acceptance rule's limits and the failing sections
    marked."""
    if not geometry.measured:
        raise ValueError(f"the weld was not measured ({geometry.why_not}): no figures along it")
    sections = geometry.sections
    failing = {(f.line, f.position_mm, f.figure) for f in geometry.failing}
    series = []
    treated = geometry.treatment != "as-welded"
    for figure, label, unit in TOE_SERIES:
        if figure.startswith("groove") and not treated:
            continue
        curves = {}
        for line in geometry.line_names():
            on_line = [s for s in sections if s.line == line]
            for side, _ in on_line[0].toes.sides():
                rows = [(s.position_mm, *figure_value(getattr(s.toes, side).figure(figure)
                                                      if getattr(s.toes, side) else None),
                         (line, s.position_mm, figure) in failing) for s in on_line]
                if not rows or all(math.isnan(r[1]) for r in rows):
                    continue
                curves[f"{line} {side} toe"] = _curve(rows)
        if curves:
            series.append(AlongWeldSeries(label, unit, curves, *_limits(geometry.acceptance, figure)))
    fillet = any(isinstance(s, FilletWeldSection) for s in sections)
    for figure, label, unit in FILLET_SERIES if fillet else SECTION_SERIES:
        curves = {line: _curve([(s.position_mm, *figure_value(s.figure(figure)),
                                 (line, s.position_mm, figure) in failing) for s in sections if s.line == line])
                  for line in geometry.line_names()}
        series.append(AlongWeldSeries(label, unit, curves, *_limits(geometry.acceptance, figure)))
    return series


def chosen_sections(geometry: WeldGeometry, per_line: int) -> list[WeldSection]:
    """Up to ``per_line`` sections per weld line: the failing first (most violations first, then
    along the line), then the uncertain, the rest filled evenly from the others along the line
    (ends left out); each line's in order along it."""
    if per_line < 0:
        raise ValueError(f"per_line must not be negative; got {per_line}")
    chosen = []
    for line in geometry.line_names():
        rows = [s for s in geometry.sections if s.line == line]
        failing = sorted((s for s in rows if s.passed is False), key=lambda s: (-len(s.violations), s.position_mm))
        uncertain = [s for s in rows if s.verdict == "uncertain"]
        picked = (failing + uncertain)[:per_line]
        rest = [s for s in rows if s not in picked]
        want = per_line - len(picked)
        if want > 0 and rest:
            picked += [rest[int(round(k))] for k in np.linspace(0, len(rest) - 1, want + 2)[1:-1]] if len(rest) > want \
                else rest
        chosen += sorted({id(s): s for s in picked}.values(), key=lambda s: s.position_mm)
    return chosen


@dataclass(frozen=True)
class SectionCut:
    """A section's picture in its plane: the measured points ``u_mm`` across the weld and ``h_mm``
    along the face normal from the section's centre, (n,) float64; ``toes`` (u, label) from the
    toes' midpoint (none unless both toes were found); ``plate`` the drawing's plate face as
    (u (2,), h (2,), label) lines; ``half_span_mm`` how far across to draw. A fillet weld's: from
    its root, ``u`` along the base plate away from the stem, its toes as points ``toe_points``
    (u, h, label)."""

    u_mm: np.ndarray
    h_mm: np.ndarray
    toes: list[tuple[float, str]]
    plate: list[tuple[np.ndarray, np.ndarray, str]]
    half_span_mm: float
    toe_points: list[tuple[float, float, str]] = ()


def section_cut(points_mm: np.ndarray, section: WeldSection | FilletWeldSection, line: WeldLineFound, *, half_width_mm: float,
                reach_mm: float, bounds_mm: tuple[Sequence[float], Sequence[float]] | None = None,
                margin_mm: float = 6.0) -> SectionCut:
    """The points of ``points_mm`` ((n, 3), specimen frame, mm: the frame the weld was measured in)
    within ``half_width_mm`` along the weld of ``section``'s centre, ``reach_mm`` across it and
    ``reach_mm / 2`` along ``line``'s face normal; the drawing's plate face from the part's
    bounding box (``bounds_mm``: min and max corner; None: no drawing) where the face normal is
    within 60 deg of z; drawn to half the weld's width plus ``margin_mm`` (half the reach plus it
    where the width is not known), at most ``reach_mm``."""
    if half_width_mm <= 0 or reach_mm <= 0:
        raise ValueError(f"half_width_mm and reach_mm must be positive; got {half_width_mm}, {reach_mm}")
    points = np.asarray(points_mm)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points_mm must be (n, 3); got shape {points.shape}")
    c = np.asarray(section.centre_specimen_mm, np.float64)
    n = np.asarray(line.face_normal, np.float64)
    a = np.asarray(line.across, np.float64)
    t = np.cross(n, a)
    d = points - c
    sel = (np.abs(d @ t) <= half_width_mm) & (np.abs(d @ a) <= reach_mm) & (np.abs(d @ n) <= reach_mm / 2)
    u, h = d[sel] @ a, d[sel] @ n
    if isinstance(section, FilletWeldSection):
        toe_points = []
        for side, _ in section.toes.sides():
            at = section.toe_specimen_mm(side)
            if at is not None:
                rel = np.asarray(at) - c
                toe_points.append((float(rel @ a), float(rel @ n), f"{side} toe"))
        legs = [v for v in (section.leg_base_mm.value, section.leg_stem_mm.value) if v is not None]
        span = (max(legs) if legs else reach_mm / 2) + margin_mm
        return SectionCut(u, h, [], [], min(span, reach_mm), toe_points)
    toes = []
    if section.toes.both():
        centre = (section.toes.minus.position_u_mm + section.toes.plus.position_u_mm) / 2
        toes = [(toe.position_u_mm - centre, f"{side} toe") for side, toe in section.toes.sides()]
    plate = []
    if bounds_mm is not None and abs(n[2]) > 0.5:
        lo, hi = bounds_mm
        z0 = hi[2] if n[2] > 0 else lo[2]
        span = np.array([-reach_mm, reach_mm])
        plate.append((span, (z0 - c[2] - span * a[2]) / n[2], "the drawing's plate face"))
    width = figure_value(section.reinforcement_width_mm)[0]
    span = (width / 2 if math.isfinite(width) else reach_mm / 2) + margin_mm
    return SectionCut(u, h, toes, plate, min(span, reach_mm))


@dataclass(frozen=True)
class ToeCloseup:
    """One toe seen close: the measured points ``t_mm`` along its plate (outward from the toe,
    away from the weld) and ``n_mm`` over the plate's face (toward the weld's side), (n,) float64,
    within ``reach_mm`` of the toe; the fitted toe drawn back (``model_t_mm``, ``model_n_mm``: the
    plate, the rounding of the measured radius and the flank at the measured angle from the corner
    at t = 0; empty where either was not measured); ``label`` names toe and figures."""

    label: str
    t_mm: np.ndarray
    n_mm: np.ndarray
    model_t_mm: np.ndarray
    model_n_mm: np.ndarray


def _toe_model(radius_mm: float, angle_deg: float, reach_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """The fitted toe (tasks.weld_fits' model without its flank's curvature): the plate n = 0
    beyond the rounding, a circle of ``radius_mm`` tangent to it and to the flank's line, which
    leaves the corner (t = 0) inward at ``angle_deg``."""
    theta = math.radians(angle_deg)
    d = radius_mm * math.tan(theta / 2)  # the rounding's ends, from the corner
    phi = np.linspace(-math.pi / 2, -math.pi / 2 - theta, 24)  # round the centre (d, r), plate to flank
    t = np.r_[reach_mm, d + radius_mm * np.cos(phi), -reach_mm * math.cos(theta)]
    n = np.r_[0.0, radius_mm + radius_mm * np.sin(phi), reach_mm * math.sin(theta)]
    return t, n


def _closeup_frames(section: WeldSection | FilletWeldSection, line: WeldLineFound) -> list[tuple]:
    """Each toe drawn close: (side, toe, where it is (specimen frame), outward along its plate,
    toward the weld's side over it)."""
    normal, across = np.asarray(line.face_normal, np.float64), np.asarray(line.across, np.float64)
    centre = np.asarray(section.centre_specimen_mm, np.float64)
    toes = []
    if isinstance(section, FilletWeldSection):
        for side, toe in section.toes.sides():
            if toe is not None:
                outward = np.asarray(section.base_direction if side == "base" else section.stem_direction, np.float64)
                up = normal if side == "base" else across  # toward the weld's side: up from the base, out from the stem
                toes.append((side, toe, np.asarray(section.toe_specimen_mm(side)), outward, up))
    elif section.toes.both():
        mid = (section.toes.minus.position_u_mm + section.toes.plus.position_u_mm) / 2
        for side, toe in section.toes.sides():
            sign = -1.0 if side == "minus" else 1.0
            toes.append((side, toe, centre + (toe.position_u_mm - mid) * across, sign * across, normal))
    return toes


def _box_bound(axes: list[np.ndarray], limits: list[float], along: np.ndarray) -> tuple[float, float]:
    """How far from its centre a point can be whose components along ``axes`` (3 vectors, not
    necessarily orthonormal) are within ``limits``: |d| <= ||E^-1|| ||limits||; and how far its
    component along ``along``: d = E^-1 y, |y_i| <= limits_i, so |along . d| <= sum |(along E^-1)_i|
    limits_i. (inf, inf) where the axes do not span space."""
    E = np.array(axes, np.float64)
    if abs(np.linalg.det(E)) < 1e-9:
        return math.inf, math.inf
    inverse = np.linalg.inv(E)
    return (float(np.linalg.norm(inverse, 2) * np.linalg.norm(limits)),
            float(np.abs(np.asarray(along, np.float64) @ inverse) @ np.abs(np.asarray(limits, np.float64))))


def near_sections(points_mm: np.ndarray, sections: Sequence[WeldSection | FilletWeldSection], line: WeldLineFound, *,
                  half_width_mm: float, reach_mm: float,
                  closeup_reach_mm: float = CLOSEUP_REACH_MM) -> list[np.ndarray]:
    """For each of ``sections`` (of ``line``), the points of ``points_mm`` ((n, 3)) that
    ``section_cut`` (``half_width_mm``, ``reach_mm``) and ``toe_closeups`` (``half_width_mm``,
    ``closeup_reach_mm``) can select, in their order: those within a box around each selection's
    bounding sphere and within the thin slab across the line the selection's box spans (a
    superset; both give the same answer on it as on all points, and read a section's few thousand
    points instead of a specimen's millions). The points are projected on the line and sorted
    along it once; each slab is found by bisection, not by a scan of the millions."""
    points = np.asarray(points_mm, np.float64)
    n, a = np.asarray(line.face_normal, np.float64), np.asarray(line.across, np.float64)
    t = np.cross(n, a)
    along = points @ t
    order = np.argsort(along, kind="stable")
    sorted_along = along[order]
    out = []
    for section in sections:
        centre = np.asarray(section.centre_specimen_mm, np.float64)
        boxes = [(centre, *_box_bound([t, a, n], [half_width_mm, reach_mm, reach_mm / 2], t))]
        boxes += [(np.asarray(at, np.float64),
                   *_box_bound([t, outward, up], [half_width_mm, closeup_reach_mm, closeup_reach_mm], t))
                  for _, _, at, outward, up in _closeup_frames(section, line)]
        if not all(math.isfinite(r) and math.isfinite(w) for _, r, w in boxes):
            out.append(points)
            continue
        found = []
        for at, radius, slab_half in boxes:
            radius = radius * (1 + 1e-9) + 1e-9  # the bounds' own rounding
            middle, half = float(at @ t), slab_half * (1 + 1e-9) + 1e-9
            # a superset by bisection (widened past the comparison's rounding), then the exact test
            lo = int(np.searchsorted(sorted_along, middle - 2 * half, side="left"))
            hi = int(np.searchsorted(sorted_along, middle + 2 * half, side="right"))
            slab = np.sort(order[lo:hi])
            slab = slab[np.abs(along[slab] - middle) <= half]
            inside = np.all(np.abs(points[slab] - at) <= radius, axis=1)
            found.append(slab[inside])
        out.append(points[distinct(np.concatenate(found))])
    return out


def toe_closeups(points_mm: np.ndarray, section: WeldSection | FilletWeldSection, line: WeldLineFound, *,
                 half_width_mm: float, reach_mm: float = CLOSEUP_REACH_MM) -> list[ToeCloseup]:
    """Each measured toe of ``section`` seen close (``ToeCloseup``), from the points of
    ``points_mm`` ((n, 3), specimen frame) within ``half_width_mm`` of the section along the weld;
    a butt weld's toes along the plate across the weld, a fillet weld's base toe along the base
    and its stem toe along the stem. The plate's level near the toe (the median over its plate's
    side, 1-2.5 mm out) is taken off, so that a misaligned plate is drawn level."""
    points = np.asarray(points_mm, np.float64)
    along = np.cross(np.asarray(line.face_normal, np.float64), np.asarray(line.across, np.float64))
    out = []
    for side, toe, at, outward, up in _closeup_frames(section, line):
        d = points - at
        sel = (np.abs(d @ along) <= half_width_mm) & (np.abs(d @ outward) <= reach_mm) & (np.abs(d @ up) <= reach_mm)
        t, n = d[sel] @ outward, d[sel] @ up
        plate = (t > 1.0) & (np.abs(n) < 0.5)
        if plate.any():
            n = n - float(np.median(n[plate]))
        radius, angle = figure_value(toe.toe_radius_mm)[0], figure_value(toe.flank_angle_deg)[0]
        model = _toe_model(radius, angle, reach_mm) if math.isfinite(radius) and math.isfinite(angle) and radius > 0 \
            else (np.zeros(0), np.zeros(0))
        label = (f"{section.line} {side} toe at {section.position_mm:g} mm: r {radius:.2f} mm, angle {angle:.1f} deg"
                 if model[0].size else f"{section.line} {side} toe at {section.position_mm:g} mm (radius or angle not measured)")
        out.append(ToeCloseup(label, t, n, *model))
    return out
