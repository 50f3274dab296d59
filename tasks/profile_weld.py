"""A butt weld's section measured on a scanned profile alone: no nominal frame, no plate window
from a drawing. Each plate is found from its end of the profile inward (the profile must start
and end on a plate), each toe fitted where the surface leaves its plate.

A profile is ``u`` across the weld (mm) and ``h`` its height (mm, along the plates' normal), in
any order. Per profile:

- spikes (one or a few points off their neighbours: scanner returns) are dropped: off the
  running median of ``spike_window`` points by more than ``spike_sigmas`` robust sigmas and
  ``spike_min_mm``; a running median follows a monotone flank and a sharp toe exactly;
- each plate: the lowest line through the outer ``seed_fraction`` of its side (the flank's points lie
  above it: ``tasks.weld_fits.fit_plate_line``), grown inward to where the surface rises
  ``toe_threshold_mm`` above it for ``rise_run_mm`` on end (the toe's first guess), refitted up to
  ``plate_gap_mm`` short of it (``tasks.weld_fits.fit_plate_line``);
- each toe: ``tasks.weld_fits.fit_toe`` (flank, toe fillet, undercut) on the height over its
  plate, fitted again around the toe it found (the window's flank is then the flank's first
  ``toe_window_mm[0]``: a parabola holds a curved cap's flank that far, not across its top); every 1-sigma is scaled by the residuals' serial correlation (a scanner's noise is
  correlated from point to point: lag-one rho gives the factor sqrt((1 + rho) / (1 - rho)));
- the toe radius is resolved when the radii the points allow (the profile likelihood,
  ``tasks.weld_fits.toe_radius_range``, at ``bound_sigmas``) exclude both a sharp corner and the
  fit's 10 mm ceiling, and the fitted radius is at least the point spacing and above its 1-sigma;
  otherwise it is reported as "below X", X the largest radius the points allow, never as a number,
  and the toe is fitted again with its radius held at the smallest the points allow (a sharp corner
  where they allow one): its position, angle and undercut are that fit's
  (``tasks.weld_fits.toe_at_radius``), so that a radius the points cannot tell is not what sets them;
- reinforcement height over the line between the toes on their plates
  (``tasks.weld_geometry.peak_rise``), width between the toes, misalignment of the plates at the
  weld's centre.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import median_filter

from tasks.weld_fits import (TOE_RADIUS_BOUNDS_MM, Measured, SectionSettings, ToeFit, fit_groove, fit_plate_line,
                             fit_toe, toe_at_radius, toe_radius_range)
from tasks.weld_geometry import SectionMeasurement, peak_rise

__all__ = ["ProfileSettings", "ToeResult", "ProfileResult", "drop_spikes", "measure_profile"]

_NAN = float("nan")
_R_FLOOR_MM, _R_CEILING_MM = TOE_RADIUS_BOUNDS_MM  # tasks.weld_fits fits the toe radius between these


@dataclass(frozen=True)
class ProfileSettings:
    """How a scanned profile is read (mm); ``schemas.profile_weld.MeasureWeldConfig`` gives them."""

    toe_window_mm: tuple[float, float]  # the toe fit: this far onto the flank, this far onto the plate
    toe_threshold_mm: float  # a rise this high over the plate ...
    rise_run_mm: float  # ... for this long starts the weld
    seed_fraction: float  # each plate's first line: on this outer fraction of its side (under the flank's points)
    plate_gap_mm: float  # a plate's line ends this far short of the toe's first guess
    min_plate_mm: float  # less plate than this beside a toe: the toe is not measured
    undercut_min_depth_mm: float
    groove_min_depth_mm: float  # treated toes (HFMI grooves), as tasks.weld_fits.fit_groove reads them
    groove_plate_gap_mm: float
    spike_window: int  # points in the running median that finds spikes (odd)
    spike_sigmas: float
    spike_min_mm: float
    bound_sigmas: float  # the radius interval's width, in sigmas (profile likelihood)
    min_points: int

    def section_settings(self) -> SectionSettings:
        """The settings ``tasks.weld_fits`` reads (its plate window unused here)."""
        return SectionSettings(plate_window_mm=(self.plate_gap_mm, self.plate_gap_mm + self.min_plate_mm),
                               toe_window_mm=self.toe_window_mm, toe_threshold_mm=self.toe_threshold_mm,
                               groove_min_depth_mm=self.groove_min_depth_mm, groove_plate_gap_mm=self.groove_plate_gap_mm,
                               undercut_min_depth_mm=self.undercut_min_depth_mm, height_half_width_mm=1.0,
                               min_points=self.min_points,
                               min_height_mm=0.0)  # unread: a profile's section is this module's own (_section)


@dataclass(frozen=True)
class ToeResult:
    """A toe: its fit (None: not measured, ``reason`` says why) and, where the points do not
    resolve its radius, the largest radius they allow (``fit.notch_radius`` is then NaN)."""

    fit: ToeFit | None
    radius_below_mm: float | None = None
    reason: str = ""
    radius_fitted: Measured = Measured.none()  # the fit's own radius, resolved or not (for the bench's bias table)
    plate_missing: bool = False  # no plate found beside the toe (the scan does not reach it)


@dataclass(frozen=True)
class ProfileResult:
    section: SectionMeasurement  # what tasks.weld_acceptance judges (unresolved radii NaN)
    toes: tuple[ToeResult, ToeResult]  # minus (u below the weld's centre), plus
    spikes: int  # points dropped as spikes
    spacing_mm: float  # median distance between neighbouring points along u


def drop_spikes(h: np.ndarray, *, window: int, sigmas: float, min_mm: float) -> np.ndarray:
    """Which points of a profile (``h`` (n,) mm, in order along it) are spikes: off the running
    median of ``window`` points by more than ``sigmas`` robust sigmas of those offsets and ``min_mm``."""
    if len(h) < window:
        return np.zeros(len(h), bool)
    off = h - median_filter(h, size=window, mode="nearest")
    spread = 1.4826 * float(np.median(np.abs(off)))
    return np.abs(off) > max(sigmas * spread, min_mm)


def _serial_factor(r: np.ndarray) -> float:
    """sqrt((1 + rho) / (1 - rho)) for the lag-one correlation rho of residuals in order (>= 1)."""
    if len(r) < 4 or float(r @ r) == 0:
        return 1.0
    rho = float(np.clip((r[:-1] @ r[1:]) / (r @ r), 0.0, 0.9))
    return math.sqrt((1 + rho) / (1 - rho))


def _plate(v: np.ndarray, h: np.ndarray, s: ProfileSettings):
    """One side's plate, ``v`` outward from the weld (ascending toward the profile's end): (its
    line, the toe's first guess on v) or (None, why)."""
    end = float(v.max())
    seed = v > end - s.seed_fraction * (end - float(v.min()))
    line = fit_plate_line(v[seed], h[seed], min_points=s.min_points)
    if line is None:
        return None, f"fewer than {s.min_points} points on the outer {s.seed_fraction:g} of this side"
    guess = None
    for _ in range(4):
        rel = h - line.at(v)
        above = rel > s.toe_threshold_mm
        order = np.argsort(-v)  # inward from the end
        vo, ao = v[order], above[order]
        # the first point inward from which the surface stays above for rise_run_mm
        run_start, found = None, None
        for i in range(len(vo)):
            if ao[i]:
                run_start = i if run_start is None else run_start
                if vo[run_start] - vo[i] >= s.rise_run_mm:
                    found = run_start
                    break
            else:
                run_start = None
        if found is None:
            return None, f"the surface never rises {s.toe_threshold_mm:g} mm over the plate for {s.rise_run_mm:g} mm"
        new_guess = float(vo[found])
        keep = (v > new_guess + s.plate_gap_mm)
        if end - (new_guess + s.plate_gap_mm) < s.min_plate_mm:
            return None, (f"{end - new_guess:.2f} mm of plate between the toe and the profile's end "
                          f"({s.plate_gap_mm + s.min_plate_mm:g} mm needed)")
        refit = fit_plate_line(v[keep], h[keep], min_points=s.min_points)
        if refit is None:
            return None, f"fewer than {s.min_points} plate points beside the toe"
        line = refit
        if guess is not None and abs(new_guess - guess) < 1e-9:
            break
        guess = new_guess
    return line, new_guess


def _scaled(m: Measured, f: float) -> Measured:
    return Measured(m.value, m.sigma * f)


def measure_profile(u: np.ndarray, h: np.ndarray, *, settings: ProfileSettings, treated: bool, line: str,
                    position_mm: float, to_frame, toe_guess_u: dict[str, float] | None = None) -> ProfileResult:
    """One scanned section: ``u`` (n,) across the weld, ``h`` (n,) height, mm, float64, any order.
    ``treated``: a toe is first looked for as an HFMI groove (``fit_groove``; its radius is the
    groove's circle, not bounded here). ``to_frame(u, h)``: the 3-D point (the scan's frame) of a
    profile position. ``toe_guess_u``: per side ("minus", "plus"), where on u to start its toe's
    fit instead of where the surface first rises off the plate (the neighbouring sections' toe)."""
    u, h = np.asarray(u, np.float64), np.asarray(h, np.float64)
    if u.shape != h.shape or u.ndim != 1:
        raise ValueError(f"u and h must be (n,) arrays of one length, got {u.shape} and {h.shape}")
    order = np.argsort(u)
    u, h = u[order], h[order]
    spikes = drop_spikes(h, window=settings.spike_window, sigmas=settings.spike_sigmas, min_mm=settings.spike_min_mm)
    u, h = u[~spikes], h[~spikes]
    spacing = float(np.median(np.diff(u))) if len(u) > 1 else _NAN
    none = Measured.none()
    centre = float(u[np.argmax(median_filter(h, size=settings.spike_window, mode="nearest"))]) if len(u) else 0.0
    fitting = settings.section_settings()
    results, plates = [], []
    for side, sign in (("minus", -1), ("plus", 1)):
        half = sign * (u - centre) > 0
        v, hv = sign * (u[half] - centre), h[half]
        if len(v) < settings.min_points:
            results.append(ToeResult(None, reason=f"fewer than {settings.min_points} points on this side of the weld",
                                     plate_missing=True))
            plates.append(None)
            continue
        plate, guess = _plate(v, hv, settings)
        plates.append(plate)
        if plate is None:
            results.append(ToeResult(None, reason=guess, plate_missing=True))
            continue
        if toe_guess_u and side in toe_guess_u:
            guess = sign * (toe_guess_u[side] - centre)
        rel = hv - plate.at(v)
        groove = fit_groove(v, rel, settings=fitting, side=side, toe_guess_v=guess) if treated else None
        if groove is not None:
            results.append(ToeResult(ToeFit(**{**groove.__dict__, "position_u_mm": centre + sign * groove.position_u_mm})))
            continue
        fit = fit_toe(v, rel, settings=fitting, side=side, toe_guess_v=guess)
        if fit is not None:  # again around the toe found: the window's flank then starts at the toe
            guess = fit.position_u_mm
            fit = fit_toe(v, rel, settings=fitting, side=side, toe_guess_v=guess)
        if fit is None:
            results.append(ToeResult(None, reason=f"fewer than {settings.min_points} points around the toe"))
            continue
        on_plate = v > guess + max(settings.toe_window_mm[1], settings.plate_gap_mm)  # the noise's serial correlation, off the plate's line
        factor = _serial_factor(rel[on_plate][np.argsort(v[on_plate])])
        variance = fit.rms_mm ** 2 * factor ** 2
        lowest, highest = toe_radius_range(v, rel, settings=fitting, toe_guess_v=guess, fit=fit,
                                           threshold_mm2=settings.bound_sigmas ** 2 * variance)
        radius = raw = _scaled(fit.notch_radius, factor)
        below = None
        # resolved: the allowed radii are closed on both sides (a sharp corner and the fit's ceiling
        # both excluded), the radius is at least the point spacing and larger than its 1-sigma
        # (the wider of the covariance's and the allowed interval's half width over bound_sigmas)
        radius = raw = Measured(raw.value, max(raw.sigma, (highest - lowest) / (2 * settings.bound_sigmas)))
        if not (lowest > _R_FLOOR_MM * 1.05 and highest < _R_CEILING_MM * 0.95 and raw.value >= spacing
                and raw.sigma < raw.value):
            below, radius = round(float(max(highest, spacing)), 4), none
            if math.isfinite(lowest):
                fit = toe_at_radius(v, rel, settings=fitting, toe_guess_v=guess, fit=fit, radius_mm=lowest)
        fit = ToeFit(side=side, position_u_mm=centre + sign * fit.position_u_mm,
                     position_sigma_mm=fit.position_sigma_mm * factor,
                     flank_angle_deg=_scaled(fit.flank_angle_deg, factor), notch_radius=radius,
                     undercut_depth=_scaled(fit.undercut_depth, factor), groove=None, rms_mm=fit.rms_mm,
                     n_points=fit.n_points, note=f"noise factor {factor:.2f} (serial correlation)")
        results.append(ToeResult(fit, below, radius_fitted=raw))
    section = _section(u, h, plates, results, centre, line=line, position_mm=position_mm, to_frame=to_frame,
                       spikes=int(spikes.sum()))
    return ProfileResult(section, (results[0], results[1]), int(spikes.sum()), spacing)


def _section(u, h, plates, results, centre, *, line, position_mm, to_frame, spikes) -> SectionMeasurement:
    """The section's figures from its plates (on v, each side) and toes."""
    none = Measured.none()
    toes = tuple(r.fit for r in results)
    height = width = axial = angle = none
    note = "; ".join(f"{side}: {r.reason}" for side, r in zip(("minus", "plus"), results) if r.reason)
    # the plates' lines on v (outward) back on u: minus v = c - u, plus v = u - c
    a_slope, a_int = (-plates[0].slope, plates[0].intercept + plates[0].slope * centre) if plates[0] else (0.0, _NAN)
    if plates[0] is not None and plates[1] is not None:
        b_slope, b_int = plates[1].slope, plates[1].intercept - plates[1].slope * centre
        axial = Measured(plates[1].intercept - plates[0].intercept,
                         math.sqrt(max(plates[0].cov[1, 1] + plates[1].cov[1, 1], 0.0)))
        angle = Measured(math.degrees(math.atan(b_slope) - math.atan(a_slope)),
                         math.degrees(math.sqrt(max(plates[0].cov[0, 0] + plates[1].cov[0, 0], 0.0))))
        if toes[0] is not None and toes[1] is not None:
            u0, u1 = toes[0].position_u_mm, toes[1].position_u_mm
            width = Measured(u1 - u0, math.hypot(toes[0].position_sigma_mm, toes[1].position_sigma_mm))
            z0, z1 = a_slope * u0 + a_int, b_slope * u1 + b_int
            between = (u > u0) & (u < u1)
            height = peak_rise(u[between], h[between] - (z0 + (z1 - z0) * (u[between] - u0) / max(u1 - u0, 1e-9)))
            centre = (u0 + u1) / 2
    base = a_slope * centre + a_int if plates[0] is not None else float(np.median(h)) if len(h) else 0.0
    if spikes:
        note = "; ".join(x for x in (note, f"{spikes} spike point(s) dropped") if x)
    return SectionMeasurement(line, position_mm, tuple(float(x) for x in to_frame(centre, base)), height, width, axial,
                              angle, toes, len(u) + spikes, note)
