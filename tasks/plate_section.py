"""The cross-section of a plate-like part (a butt-welded plate, a dog-bone) across its weld, from
its measured points: the outline ``tasks.section_model`` meshes and pulls.

The section is the plane through ``frame.origin`` normal to ``frame.along`` (along the weld); in it
x runs along ``frame.across`` (the pull, across the weld) and y along ``frame.up`` (the top face's
outward normal, through the thickness). The points within ``half_width_mm`` of the plane are read
as two profiles, the top face (normals within ``min_normal_cos`` of up) and the bottom face
(within it of down): per ``bin_mm`` along x the median height of each, bins without points filled
along the profile between the bins around them, then smoothed over ``smooth_mm`` either side (a
quadratic Savitzky-Golay filter and a Gaussian of one bin: the measured points' noise would
otherwise be read as notches). The outline is the two profiles
where both faces were measured, cut straight across ``cut_mm`` inside either end of that range
(the unscanned ends, which a Poisson surface closes with rounded caps, are not part of it).
Arrays in, arrays out: no files, no solver."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.signal import savgol_filter

from tasks.section_model import PlaneSection

__all__ = ["SectionFrame", "PlateProfile", "plate_profile", "profile_section", "to_section"]


@dataclass(frozen=True)
class SectionFrame:
    """The section plane: a point of it (mm) and three orthonormal directions (x ``across``, y
    ``up``, the plane's normal ``along``), in the frame of the points."""

    origin: np.ndarray
    across: np.ndarray
    up: np.ndarray
    along: np.ndarray


@dataclass(frozen=True)
class PlateProfile:
    """The two faces' heights along x (mm, bin centres): ``top_mm`` and ``bottom_mm`` smoothed,
    ``measured_top`` / ``measured_bottom`` whether the bin held points; NaN outside the range both
    faces span."""

    x_mm: np.ndarray
    top_mm: np.ndarray
    bottom_mm: np.ndarray
    measured_top: np.ndarray
    measured_bottom: np.ndarray

    @property
    def span_mm(self) -> tuple[float, float]:
        both = np.isfinite(self.top_mm) & np.isfinite(self.bottom_mm)
        return (float(self.x_mm[both][0]), float(self.x_mm[both][-1])) if both.any() else (np.nan, np.nan)

    def thickness_mm(self, x_from: float, x_to: float) -> float:
        """The median thickness (top less bottom) over the measured bins of both faces in [x_from, x_to]."""
        sel = (self.x_mm >= min(x_from, x_to)) & (self.x_mm <= max(x_from, x_to)) & self.measured_top & self.measured_bottom
        return float(np.median(self.top_mm[sel] - self.bottom_mm[sel])) if sel.any() else float("nan")


def to_section(frame: SectionFrame, points: np.ndarray) -> np.ndarray:
    """(n, 3) points -> (n, 3) section coordinates (x across, y up, s along), mm."""
    rel = np.asarray(points, np.float64) - frame.origin
    return np.c_[rel @ frame.across, rel @ frame.up, rel @ frame.along]


def _face(x: np.ndarray, y: np.ndarray, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The median y per bin (NaN where none) and whether the bin held points."""
    k = len(edges) - 1
    b = np.searchsorted(edges, x, side="right") - 1
    ok = (b >= 0) & (b < k)
    b, y = b[ok], y[ok]
    order = np.lexsort((y, b))
    b, y = b[order], y[order]
    starts = np.flatnonzero(np.r_[True, b[1:] != b[:-1]])
    counts = np.diff(np.r_[starts, len(b)])
    median = np.full(k, np.nan)
    # the median of each bin's sorted heights (the mean of the two middle ones for an even count)
    lo, hi = starts + (counts - 1) // 2, starts + counts // 2
    median[b[starts]] = 0.5 * (y[lo] + y[hi])
    return median, np.isfinite(median)


def _filled_smoothed(values: np.ndarray, measured: np.ndarray, lo: int, hi: int, half_window_bins: float) -> np.ndarray:
    """The face's heights from bin ``lo`` to ``hi``: empty bins filled along the profile, then a
    quadratic Savitzky-Golay filter of ``half_window_bins`` either side (it keeps a toe's curvature
    where a Gaussian of the same reach blunts it) and a Gaussian of one bin (the Savitzky-Golay
    filter lets through some of the noise at the bins' own scale, which a notch model reads)."""
    out = np.full(len(values), np.nan)
    idx = np.arange(lo, hi + 1)
    have = np.flatnonzero(measured[lo:hi + 1]) + lo
    filled = np.interp(idx, have, values[have])
    half = int(round(half_window_bins))
    if half >= 2 and len(filled) > 2 * half + 1:
        filled = gaussian_filter1d(savgol_filter(filled, 2 * half + 1, 2, mode="interp"), 1.0, mode="nearest")
    out[lo:hi + 1] = filled
    return out


def plate_profile(points: np.ndarray, normals: np.ndarray, frame: SectionFrame, *, half_width_mm: float,
                  bin_mm: float, smooth_mm: float, min_normal_cos: float = 0.5) -> PlateProfile | None:
    """The section's two face profiles (see the module's description); None when either face has
    fewer than ten bins with points."""
    if half_width_mm <= 0 or bin_mm <= 0 or smooth_mm < 0:
        raise ValueError(f"half_width_mm and bin_mm must be positive and smooth_mm not negative, got "
                         f"{half_width_mm}, {bin_mm}, {smooth_mm}")
    points = np.asarray(points, np.float64)
    normals = np.asarray(normals, np.float64)
    if points.ndim != 2 or points.shape[1:] != (3,) or normals.shape != points.shape:
        raise ValueError(f"points and normals must be (n, 3) arrays of one shape, got {points.shape} and {normals.shape}")
    xys = to_section(frame, points)
    slab = np.abs(xys[:, 2]) <= half_width_mm
    xys, facing = xys[slab], normals[slab] @ frame.up
    if not slab.any():
        return None
    x0 = np.floor(xys[:, 0].min() / bin_mm) * bin_mm
    edges = x0 + bin_mm * np.arange(int(np.ceil((xys[:, 0].max() - x0) / bin_mm)) + 2)
    top, has_top = _face(xys[facing > min_normal_cos, 0], xys[facing > min_normal_cos, 1], edges)
    bottom, has_bottom = _face(xys[facing < -min_normal_cos, 0], xys[facing < -min_normal_cos, 1], edges)
    if has_top.sum() < 10 or has_bottom.sum() < 10:
        return None
    lo = max(np.flatnonzero(has_top)[0], np.flatnonzero(has_bottom)[0])
    hi = min(np.flatnonzero(has_top)[-1], np.flatnonzero(has_bottom)[-1])
    if hi - lo < 10:
        return None
    half = smooth_mm / bin_mm
    return PlateProfile(x_mm=0.5 * (edges[:-1] + edges[1:]), top_mm=_filled_smoothed(top, has_top, lo, hi, half),
                        bottom_mm=_filled_smoothed(bottom, has_bottom, lo, hi, half), measured_top=has_top,
                        measured_bottom=has_bottom)


def profile_section(profile: PlateProfile, *, cut_mm: float, fine_mm: np.ndarray) -> PlaneSection:
    """The section's outline: the bottom face left to right, the right cut, the top face right to
    left, the left cut (counter-clockwise), ``cut_mm`` inside the range both faces span; the four
    corners kept, the elements finest at ``fine_mm`` ((m, 2) section coordinates)."""
    x_lo, x_hi = profile.span_mm
    x_lo, x_hi = x_lo + cut_mm, x_hi - cut_mm
    if not x_hi > x_lo:
        raise ValueError(f"the section spans {profile.span_mm[1] - profile.span_mm[0]:.1f} mm: nothing is left "
                         f"{cut_mm:g} mm inside either end")
    inner = (profile.x_mm > x_lo) & (profile.x_mm < x_hi)
    x = np.r_[x_lo, profile.x_mm[inner], x_hi]
    top = np.interp(x, profile.x_mm[np.isfinite(profile.top_mm)], profile.top_mm[np.isfinite(profile.top_mm)])
    bottom = np.interp(x, profile.x_mm[np.isfinite(profile.bottom_mm)], profile.bottom_mm[np.isfinite(profile.bottom_mm)])
    outline = np.r_[np.c_[x, bottom], np.c_[x[::-1], top[::-1]]]
    n = len(x)
    return PlaneSection(outline, fine_mm=np.asarray(fine_mm, np.float64).reshape(-1, 2), corners=(0, n - 1, n, 2 * n - 1))
