"""A fillet weld measured in sections across its root line (a T-joint's or a cruciform's weld
between a base plate and a stem standing on it): each toe's radius, angle and undercut (the butt
weld's fits, ``tasks.weld_fits``), the two legs, the throat and the convexity, each with its 1-sigma.

A section is read in its own plane: ``a`` outward along the base plate from the stem's face, ``b``
up the stem from the base plate's face (mm; the nominal root at the origin). Each plate's line is
fitted over ``plate_window_mm`` from the nominal root (the base's over ``a``, the stem's over ``b``:
the face nearest the weld's side there, the points within a quarter of the window's start of it);
the root is where the two lines cross, the nominal one needs only to be within a few millimetres. The points on the weld's side are split by the bisector of the plates' angle: those nearer
the base make the base toe's profile (``v`` along the base from the root, ``h`` above the base's
line), those nearer the stem the stem toe's (``v`` up the stem, ``h`` out from its line). Each
profile is read as a butt weld's toe is (outward, the weld falling onto its plate): the toe guess
where the running median of the height first drops under ``toe_threshold_mm``, then ``fit_toe``
(``fit_groove`` first where treated).

- legs: from the root to each toe along its plate (where the flank's line meets the plate: the
  corner the toe's rounding replaces, as ISO 5817 and the IIW measure legs);
- convexity: the weld face's largest rise above the chord between the toes (a running median of
  five points along the chord; negative: concave);
- throat: the height of the triangle root-toe-toe over its chord (the design throat ``a``), less
  the concavity where the face falls under the chord.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tasks.weld_fits import (Measured, PlateFit, SectionSettings, ToeFit, fit_groove, fit_plate_line, fit_toe, propagate,
                             running_median)

__all__ = ["FilletSection", "FilletLine", "measure_fillet_section", "measure_fillet_line", "fillet_frame"]


@dataclass(frozen=True)
class FilletSection:
    """One section of a fillet weld: the root (a, b; mm, the plates' lines crossing), the base
    plate's direction outward and the stem's upward (unit, in (a, b)), the angle between them
    (deg), the toes (``position_u_mm`` along their plate from the root), legs, throat, convexity;
    ``note`` says why a figure is missing."""

    root_ab_mm: tuple[float, float]
    base_direction: tuple[float, float]
    stem_direction: tuple[float, float]
    plates_angle_deg: float
    base_toe: ToeFit | None
    stem_toe: ToeFit | None
    leg_base: Measured
    leg_stem: Measured
    throat: Measured
    convexity: Measured
    n_points: int
    note: str = ""

    def toe_ab_mm(self, plate: str) -> tuple[float, float] | None:
        """Where the toe on ``plate`` ("base" or "stem") is in the section's (a, b)."""
        fit, direction = (self.base_toe, self.base_direction) if plate == "base" else (self.stem_toe, self.stem_direction)
        if fit is None:
            return None
        return (self.root_ab_mm[0] + fit.position_u_mm * direction[0],
                self.root_ab_mm[1] + fit.position_u_mm * direction[1])


def _toe(v: np.ndarray, h: np.ndarray, *, settings: SectionSettings, side: str, treated: bool) -> tuple[ToeFit | None, str]:
    """One toe's fit on its profile (v outward from the root, h over the plate), or why not."""
    order = np.argsort(v)
    v, h = v[order], h[order]
    near = settings.plate_window_mm[0]
    inside = v < near
    v, h = v[inside], h[inside]
    if len(v) < settings.min_points:
        return None, f"{side} toe: {len(v)} points between the root and the plate's window"
    smooth = running_median(h)
    raised = smooth > settings.toe_threshold_mm
    if not raised.any():
        return None, f"{side} toe: no weld above the {side} plate"
    low = np.flatnonzero(~raised & (v > v[raised].min()))
    if len(low) == 0:
        return None, f"{side} toe: the weld does not come down onto the {side} plate before {near:g} mm"
    guess = float(v[low[0]])
    fit = fit_groove(v, h, settings=settings, side=side, toe_guess_v=guess) if treated else None
    if fit is None:
        fit = fit_toe(v, h, settings=settings, side=side, toe_guess_v=guess)
    return fit, "" if fit is not None else f"{side} toe: too few points around {guess:.2f} mm"


def fillet_frame(base: PlateFit, stem: PlateFit) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The root where the base's line (b = slope a + intercept) and the stem's (a = slope b +
    intercept) cross, the base's unit direction outward and the stem's upward (a, b), and the
    angle between them (deg)."""
    a = (stem.slope * base.intercept + stem.intercept) / (1 - stem.slope * base.slope)
    root = np.array([a, base.slope * a + base.intercept])
    e_base = np.array([1.0, base.slope]) / math.hypot(1.0, base.slope)
    e_stem = np.array([stem.slope, 1.0]) / math.hypot(1.0, stem.slope)
    return root, e_base, e_stem, math.degrees(math.acos(float(np.clip(e_base @ e_stem, -1, 1))))


def measure_fillet_section(a: np.ndarray, b: np.ndarray, *, settings: SectionSettings, treated: bool) -> FilletSection:
    """One section's figures from its points' ``a``, ``b`` (n,) (mm; see the module's description)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.shape != b.shape or a.ndim != 1:
        raise ValueError(f"a and b must be (n,) arrays of one length, got {a.shape} and {b.shape}")
    none = Measured.none()

    def failed(why: str) -> FilletSection:
        return FilletSection((math.nan, math.nan), (1.0, 0.0), (0.0, 1.0), math.nan, None, None, none, none, none, none,
                             len(a), why)

    near, far = settings.plate_window_mm
    band = near / 4
    # each plate's face in its window: the one nearest the weld's side (the base's top over its
    # bottom, the stem's welded face over its other one), within a quarter of the window's start
    on_base, on_stem = (a >= near) & (a <= far) & (np.abs(b) <= far), (b >= near) & (b <= far) & (np.abs(a) <= far)
    if on_base.any():
        on_base &= np.abs(b - np.percentile(b[on_base], 90)) <= band
    if on_stem.any():
        on_stem &= np.abs(a - np.percentile(a[on_stem], 90)) <= band
    base = fit_plate_line(a[on_base], b[on_base], min_points=settings.min_points)
    stem = fit_plate_line(b[on_stem], a[on_stem], min_points=settings.min_points)
    if base is None or stem is None:
        which = " and ".join(w for w, f in (("base", base), ("stem", stem)) if f is None)
        return failed(f"the {which} plate's window ({near:g}-{far:g} mm from the root) has too few points")
    root, e_base, e_stem, angle = fillet_frame(base, stem)
    n_base = np.array([-e_base[1], e_base[0]])  # up from the base, toward the stem's side
    n_stem = np.array([e_stem[1], -e_stem[0]])  # out from the stem, toward the base's side
    rel = np.stack([a, b], 1) - root
    v_base, h_base, v_stem, h_stem = rel @ e_base, rel @ n_base, rel @ e_stem, rel @ n_stem
    weld_side = (h_base > -band) & (h_stem > -band)
    nearer_base = weld_side & (h_base <= h_stem)
    nearer_stem = weld_side & (h_base > h_stem)
    notes = []
    base_toe, why = _toe(v_base[nearer_base], h_base[nearer_base], settings=settings, side="base", treated=treated)
    notes.append(why)
    stem_toe, why = _toe(v_stem[nearer_stem], h_stem[nearer_stem], settings=settings, side="stem", treated=treated)
    notes.append(why)
    leg_base = none if base_toe is None else Measured(base_toe.position_u_mm, base_toe.position_sigma_mm)
    leg_stem = none if stem_toe is None else Measured(stem_toe.position_u_mm, stem_toe.position_sigma_mm)
    throat = convexity = none
    if base_toe is not None and stem_toe is not None:
        B, S = leg_base.value * e_base, leg_stem.value * e_stem
        chord = S - B
        length = float(np.linalg.norm(chord))
        out = np.array([chord[1], -chord[0]]) / length  # away from the root
        if out @ B < 0:
            out = -out
        t = (rel - B) @ chord / length ** 2
        face = weld_side & (t > 0.1) & (t < 0.9)
        if face.sum() >= settings.min_points:
            order = np.argsort(t[face])
            rise = ((rel[face] - B) @ out)[order]
            smooth = running_median(rise)
            k = int(np.nanargmax(smooth))
            spread = float(np.std(rise - smooth)) if len(rise) > 5 else math.nan
            convexity = Measured(float(smooth[k]), spread / math.sqrt(5))
        sin = math.sin(math.radians(angle))

        def design(p):  # the triangle's height over its chord: legs p[0], p[1], the plates' angle
            return p[0] * p[1] * sin / math.sqrt(p[0] ** 2 + p[1] ** 2 - 2 * p[0] * p[1] * math.cos(math.radians(angle)))

        legs = np.array([leg_base.value, leg_stem.value])
        cov = np.diag([leg_base.sigma ** 2, leg_stem.sigma ** 2])
        concavity = min(convexity.value, 0.0) if math.isfinite(convexity.value) else 0.0
        throat = Measured(design(legs) + concavity, math.hypot(propagate(design, legs, cov),
                                                               convexity.sigma if concavity < 0 else 0.0))
    return FilletSection((float(root[0]), float(root[1])), (float(e_base[0]), float(e_base[1])),
                         (float(e_stem[0]), float(e_stem[1])), angle, base_toe, stem_toe, leg_base, leg_stem, throat,
                         convexity, len(a), "; ".join(n for n in notes if n))


@dataclass(frozen=True)
class FilletLine:
    """A fillet weld's sections along its root line: ``origin`` (3,) the line's first point,
    ``along``, ``out`` (the base plate's face away from the stem) and ``up`` (the stem's face away
    from the base) unit (3,), the frame the points came in; (position along the line, section) in
    order; the extent along the line where the points reach."""

    name: str
    origin: np.ndarray
    along: np.ndarray
    out: np.ndarray
    up: np.ndarray
    sections: list[tuple[float, FilletSection]]
    extent_mm: tuple[float, float]

    def to_frame(self, position_mm: float, ab) -> np.ndarray:
        """A section's (a, b) at ``position_mm`` as a point of the points' frame."""
        return self.origin + position_mm * self.along + ab[0] * self.out + ab[1] * self.up

    def direction(self, ab) -> np.ndarray:
        """A section's direction (a, b) as a vector of the points' frame."""
        return ab[0] * self.out + ab[1] * self.up


def measure_fillet_line(points: np.ndarray, root_mm: np.ndarray, out: np.ndarray, up: np.ndarray, *, name: str,
                        step_mm: float, section_half_width_mm: float, reach_mm: float, end_margin_mm: float,
                        settings: SectionSettings, treated: bool) -> FilletLine:
    """Sections every ``step_mm`` along a fillet weld's root line (``root_mm`` (k >= 2, 3): its first
    and last point, in the points' frame), ``out`` along the base plate away from the stem and
    ``up`` along the stem away from the base (unit, perpendicular to the line and to each other).
    Points within ``reach_mm`` of the root in the section's plane are read; sections run where
    they reach along the line, less ``end_margin_mm`` at each end."""
    points = np.asarray(points, np.float64)
    root = np.asarray(root_mm, np.float64)
    if points.ndim != 2 or points.shape[1:] != (3,):
        raise ValueError(f"points must be (n, 3), got {points.shape}")
    if root.ndim != 2 or root.shape[1:] != (3,) or len(root) < 2:
        raise ValueError(f"root_mm must be (k >= 2, 3), got {root.shape}")
    if step_mm <= 0 or section_half_width_mm <= 0:
        raise ValueError(f"step_mm and section_half_width_mm must be positive, got {step_mm}, {section_half_width_mm}")
    along = root[-1] - root[0]
    length = float(np.linalg.norm(along))
    along = along / length
    out, up = np.asarray(out, np.float64), np.asarray(up, np.float64)
    rel = points - root[0]
    s, a, b = rel @ along, rel @ out, rel @ up
    near = (np.abs(a) <= reach_mm) & (np.abs(b) <= reach_mm) & (s > -1) & (s < length + 1)
    s, a, b = s[near], a[near], b[near]
    empty = FilletLine(name, root[0], along, out, up, [], (0.0, 0.0))
    if len(s) < settings.min_points:
        return empty
    order = np.argsort(s, kind="stable")
    s, a, b = s[order], a[order], b[order]
    lo, hi = float(s[0]) + end_margin_mm, float(s[-1]) - end_margin_mm
    sections = []
    if hi >= lo:
        for pos in np.arange(np.ceil(lo / step_mm) * step_mm, hi + 1e-9, step_mm):
            i0, i1 = np.searchsorted(s, [pos - section_half_width_mm, pos + section_half_width_mm])
            try:
                sections.append((float(pos), measure_fillet_section(a[i0:i1], b[i0:i1], settings=settings,
                                                                    treated=treated)))
            except (ValueError, np.linalg.LinAlgError) as exc:  # one section's fit, not the weld's
                none = Measured.none()
                sections.append((float(pos), FilletSection((math.nan, math.nan), (1.0, 0.0), (0.0, 1.0), math.nan, None,
                                                           None, none, none, none, none, int(i1 - i0),
                                                           f"fit failed: {exc}")))
    return FilletLine(name, root[0], along, out, up, sections, (float(s[0]), float(s[-1])))
