"""Known-answer scanned profiles of a butt weld (``weldrecon measure-weld``'s bench and tests):
straight flanks at the drawn toe (flank) angle under a circular cap, a concave fillet of the
drawn toe radius tangent to flank and plate, sampled as a line scanner does, with the noise, spikes and
dropouts measured on the real scans (``bench/README.md``, "Real welds").

Truth per toe: the flank's angle to the plate; the toe position the flank's virtual corner on the
plate (``u = +-half_width_mm``: where ``tasks.weld_fits.fit_toe`` puts it); the
radius the fillet's."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter

__all__ = ["ScanNoise", "REAL_SCAN_NOISE", "add_scan_noise", "draw_butt_profile", "ScannedView", "butt_weld_views"]


@dataclass(frozen=True)
class ScanNoise:
    rms_mm: float  # off a smooth surface
    correlation_mm: float  # exp(-d / this): the noise's correlation between points d apart
    spike_rate: float  # per point
    spike_mm: tuple[float, float]  # spike size, uniform between these, either sign
    dropout_rate: float  # per point


# measured on the three realweld scans (bench/README.md, "Real welds"): RMS 0.011-0.012 mm off a
# cubic on the plates, lag-one correlation 0.57-0.64 at 0.05 mm (0.05 / -ln 0.6 = 0.098 mm), spikes
# 5e-4 - 2e-3 of the points at 0.05-1.2 mm, dropouts 3e-4 - 4e-4
REAL_SCAN_NOISE = ScanNoise(rms_mm=0.012, correlation_mm=0.098, spike_rate=1.5e-3, spike_mm=(0.05, 1.2),
                            dropout_rate=3.5e-4)


def draw_butt_profile(*, toe_radius_mm: float, toe_angle_deg: float, spacing_mm: float, height_mm: float = 4.0,
                      flank_fraction: float = 0.75, plate_mm: float = 10.0, noise: ScanNoise | None,
                      rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, float]:
    """(u, h, half_width_mm): a profile across a symmetric butt weld, mm: flat plates, a straight
    flank at ``toe_angle_deg`` up ``flank_fraction`` of the height, a circular cap tangent to it
    (level at u = 0), and a fillet of ``toe_radius_mm`` tangent to plate and flank (it must fit on
    the straight flank). The toes' virtual corners at u = +-half_width_mm. ``noise`` None: exact."""
    theta = math.radians(toe_angle_deg)
    t = math.tan(theta)
    R_cap = (1 - flank_fraction) * height_mm / (1 - math.cos(theta))
    arc_end = R_cap * math.sin(theta)  # where the cap meets the flank
    half = arc_end + flank_fraction * height_mm / t
    d = toe_radius_mm * math.tan(theta / 2)  # the fillet's tangent points from the corner
    if d * math.cos(theta) > half - arc_end:
        raise ValueError(f"a {toe_radius_mm} mm fillet does not fit on a {toe_angle_deg} deg flank of "
                         f"{flank_fraction * height_mm:g} mm")
    span = half + plate_mm
    u = np.arange(-span, span + 1e-9, spacing_mm) + rng.uniform(0, spacing_mm)
    a = np.abs(u)
    cap = height_mm - R_cap + np.sqrt(np.maximum(R_cap ** 2 - a * a, 0.0))
    flank = (half - a) * t
    fillet = toe_radius_mm - np.sqrt(np.maximum(toe_radius_mm ** 2 - (a - half - d) ** 2, 0.0))
    h = np.where(a < arc_end, cap, np.where(a < half - d * math.cos(theta), flank,
                                             np.where(a < half + d, fillet, 0.0)))
    if noise is not None:
        u, h = add_scan_noise(u, h, spacing_mm=spacing_mm, noise=noise, rng=rng)
    return u, h, half


def add_scan_noise(u: np.ndarray, h: np.ndarray, *, spacing_mm: float, noise: ScanNoise,
                   rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(u, h) of an exact profile sampled every ``spacing_mm`` (mm, (n,) each, in order along it)
    as a scanner returns it: correlated noise, spikes, dropouts (``noise``)."""
    rho = math.exp(-spacing_mm / noise.correlation_mm)
    w = rng.normal(0.0, noise.rms_mm * math.sqrt(1 - rho * rho), len(u))
    w[0] = rng.normal(0.0, noise.rms_mm)
    h = h + lfilter([1.0], [1.0, -rho], w)  # AR(1): e_i = rho e_(i-1) + w_i
    spikes = rng.random(len(u)) < noise.spike_rate
    h[spikes] += rng.choice([-1.0, 1.0], spikes.sum()) * rng.uniform(*noise.spike_mm, spikes.sum())
    keep = rng.random(len(u)) >= noise.dropout_rate
    return u[keep], h[keep]


@dataclass(frozen=True)
class ScannedView:
    """One view of a scanned weld patch: its points in its own frame (mm) and its pose."""

    points_mm: np.ndarray  # (n, 3), the view's frame
    T_world_scan: np.ndarray  # (4, 4)


def butt_weld_views(*, toe_radius_mm: float, toe_angle_deg: float, spacing_mm: float, profile_pitch_mm: float,
                    length_mm: float, height_mm: float = 3.0, plate_mm: float = 32.0,
                    x_ranges_mm: tuple[tuple[float, float], ...] = ((-100.0, 6.0), (-6.0, 100.0)),
                    noise: ScanNoise | None, rng: np.random.Generator) -> tuple[list[ScannedView], float]:
    """Views of a straight butt weld's cap on a flat plate, as a line scanner sweeping along it
    returns them (``draw_butt_profile``'s profile every ``profile_pitch_mm`` along the weld, each
    view with its own noise): world frame x across the weld (its centre x = 0), y along it (0 to
    ``length_mm``), z up from the plate's face (z = 0); each view holds the points with x in its
    range of ``x_ranges_mm``, in its own frame (turned about z and shifted, its pose
    ``T_world_scan``). Returns the views and the toes' half width (the toes' virtual corners at
    x = +-half)."""
    ys = np.arange(0.0, length_mm + 1e-9, profile_pitch_mm)
    views = []
    half = 0.0
    for k, (x0, x1) in enumerate(x_ranges_mm):
        rows = []
        for y in ys:
            u, h, half = draw_butt_profile(toe_radius_mm=toe_radius_mm, toe_angle_deg=toe_angle_deg,
                                           spacing_mm=spacing_mm, height_mm=height_mm, plate_mm=plate_mm, noise=noise,
                                           rng=rng)
            keep = (u >= x0) & (u <= x1)
            rows.append(np.column_stack([u[keep], np.full(keep.sum(), y), h[keep]]))
        world = np.concatenate(rows)
        turn = math.radians(25.0 + 50.0 * k)
        T = np.eye(4)
        T[:3, :3] = [[math.cos(turn), -math.sin(turn), 0.0], [math.sin(turn), math.cos(turn), 0.0], [0.0, 0.0, 1.0]]
        T[:3, 3] = [40.0 * k - 15.0, 10.0 - 30.0 * k, 5.0 * k + 2.0]
        views.append(ScannedView(points_mm=(world - T[:3, 3]) @ T[:3, :3], T_world_scan=T))
    return views, half
