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

from dataclasses import dataclass, replace

import numpy as np
from scipy.ndimage import gaussian_filter1d, median_filter
from scipy.signal import savgol_filter

from tasks.section_model import PlaneSection

__all__ = ["SectionFrame", "PlateProfile", "plate_profile", "profile_section", "to_section", "rounded_notches",
           "StemFace", "TeeProfile", "tee_profile", "tee_section", "drawn_tee_section", "rounded_tee",
           "drawn_profile"]


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
    if len(b) == 0:
        return np.full(k, np.nan), np.zeros(k, bool)
    order = np.lexsort((y, b))
    b, y = b[order], y[order]
    starts = np.flatnonzero(np.r_[True, b[1:] != b[:-1]])
    counts = np.diff(np.r_[starts, len(b)])
    median = np.full(k, np.nan)
    # the median of each bin's sorted heights (the mean of the two middle ones for an even count)
    lo, hi = starts + (counts - 1) // 2, starts + counts // 2
    median[b[starts]] = 0.5 * (y[lo] + y[hi])
    return median, np.isfinite(median)


def _filled_smoothed(values: np.ndarray, measured: np.ndarray, lo: int, hi: int, half_window_bins: float,
                     outward: float) -> np.ndarray:
    """The face's heights from bin ``lo`` to ``hi``: empty bins filled along the profile; a bin
    standing out of the face (``outward``: +1 where the part lies below the heights, -1 above)
    further than the median of the five around it brought back to that median (a stray point,
    spatter: the tjoint preset's one made a 0.3 mm notch beside a toe, +25 % on its factor; a dip,
    a notch or an undercut however narrow is kept); then a quadratic Savitzky-Golay filter of
    ``half_window_bins`` either side (it keeps a toe's curvature where a Gaussian of the same
    reach blunts it) and a Gaussian of one bin (the Savitzky-Golay filter lets through some of the
    noise at the bins' own scale, which a notch model reads)."""
    out = np.full(len(values), np.nan)
    idx = np.arange(lo, hi + 1)
    have = np.flatnonzero(measured[lo:hi + 1]) + lo
    filled = np.interp(idx, have, values[have])
    if len(filled) >= 5:
        filled = outward * np.minimum(outward * filled, median_filter(outward * filled, size=5, mode="nearest"))
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
    return PlateProfile(x_mm=0.5 * (edges[:-1] + edges[1:]), top_mm=_filled_smoothed(top, has_top, lo, hi, half, 1.0),
                        bottom_mm=_filled_smoothed(bottom, has_bottom, lo, hi, half, -1.0), measured_top=has_top,
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


def _closed_from_above(height: np.ndarray, step_mm: float, radius_mm: float) -> np.ndarray:
    """A face seen from above (the part below ``height``, bins ``step_mm`` apart) as a disk of
    ``radius_mm`` rolling on it from above traces it: the lowest a disk centred over each bin can
    sit without entering the part, then the lowest of the disks' undersides over each bin. Every
    concave corner sharper than the disk becomes an arc of its radius tangent to both sides;
    nothing the disk touches moves (material is only added)."""
    k = int(np.floor(radius_mm / step_mm))
    offsets = np.arange(-k, k + 1)
    drop = np.sqrt(np.maximum(radius_mm ** 2 - (offsets * step_mm) ** 2, 0.0))
    padded = np.pad(height, k, mode="edge")  # flat beyond the ends
    n = len(height)
    centre = np.max([padded[k + o:k + o + n] + d for o, d in zip(offsets, drop)], axis=0)
    centre = np.pad(centre, k, mode="edge")
    return np.min([centre[k + o:k + o + n] - d for o, d in zip(offsets, drop)], axis=0)


def rounded_notches(profile: PlateProfile, radius_mm: float) -> PlateProfile:
    """The profile with every notch of either face rounded to ``radius_mm`` at least: the face as a
    disk of that radius rolling along it outside the part traces it (a morphological closing of
    the part). A weld toe sharper than the disk, an undercut narrower than it, becomes an arc of
    its radius tangent to the plate and the flank; a notch as wide or wider (an HFMI groove of a
    larger radius) and every convex shape are kept. The IIW effective notch stress method's
    fictitious rounding (Hobbacher, IIW recommendations, r_ref = 1 mm for steel plates of 5 mm and
    thicker): the worst-case notch, a sharp one, made the reference radius."""
    if not radius_mm > 0:
        raise ValueError(f"radius_mm must be positive, got {radius_mm}")
    x = profile.x_mm
    step = float(np.median(np.diff(x)))
    out = {}
    for name, sign in (("top_mm", 1.0), ("bottom_mm", -1.0)):
        values = getattr(profile, name)
        finite = np.isfinite(values)
        rounded = np.full(len(values), np.nan)
        # each stretch of the face on its own (a T-joint's top face stops at the stem on either side)
        edges = np.flatnonzero(np.diff(np.r_[False, finite, False].astype(np.int8)))
        for lo, hi in zip(edges[::2], edges[1::2]):
            rounded[lo:hi] = sign * _closed_from_above(sign * values[lo:hi], step, radius_mm)
        out[name] = rounded
    return PlateProfile(x_mm=x, top_mm=out["top_mm"], bottom_mm=out["bottom_mm"], measured_top=profile.measured_top,
                        measured_bottom=profile.measured_bottom)


def drawn_profile(*, thickness_mm: float, caps: dict[str, tuple[float, float]], half_length_mm: float,
                  bin_mm: float) -> PlateProfile:
    """The drawn (idealised) section of a double-sided butt weld: a plate of ``thickness_mm``, its
    faces at +-thickness/2, straight and aligned, and on each face in ``caps`` ("top", "bottom":
    (width, height) mm) a cap shaped as a circular segment centred at x = 0, the plate's face
    meeting it in a sharp toe; ``half_length_mm`` either side, bins of ``bin_mm``."""
    if not (thickness_mm > 0 and half_length_mm > 0 and bin_mm > 0):
        raise ValueError(f"thickness_mm, half_length_mm and bin_mm must be positive, got {thickness_mm}, "
                         f"{half_length_mm}, {bin_mm}")
    x = np.arange(-half_length_mm, half_length_mm + bin_mm / 2, bin_mm)
    faces = {}
    for face, sign in (("top", 1.0), ("bottom", -1.0)):
        height = np.zeros(len(x))
        if face in caps:
            width, rise = caps[face]
            if not (width > 0 and rise > 0 and width < 2 * half_length_mm):
                raise ValueError(f"the {face} cap must have a positive width (under {2 * half_length_mm:g} mm) and "
                                 f"height, got {width}, {rise}")
            radius = (width ** 2 / 4 + rise ** 2) / (2 * rise)
            inside = np.abs(x) < width / 2
            height[inside] = np.sqrt(radius ** 2 - x[inside] ** 2) - (radius - rise)
        faces[face] = sign * (thickness_mm / 2 + height)
    everywhere = np.ones(len(x), bool)
    return PlateProfile(x_mm=x, top_mm=faces["top"], bottom_mm=faces["bottom"], measured_top=everywhere,
                        measured_bottom=everywhere)


@dataclass(frozen=True)
class StemFace:
    """One face of a stem standing on the base plate, in the section: ``side`` +1 where the base
    runs on toward +x from it, -1 toward -x; ``root_mm`` (x, y) where it meets the base's face (a
    fillet's root); where the part's outline leaves the base's face profile for the stem's
    (``junction_x_mm``: the top profile is the outline up to it); the face's x at heights
    ``y_mm`` from the junction up to the stem's cut (``x_mm``)."""

    side: int
    root_mm: np.ndarray
    junction_x_mm: float
    y_mm: np.ndarray
    x_mm: np.ndarray


@dataclass(frozen=True)
class TeeProfile:
    """A T-joint's section: the base plate's faces as a ``PlateProfile`` (the top face, fillets
    included, up to each stem face's junction) and the stem's two faces up to ``stem_top_mm``. A
    cruciform's also has a stem on the bottom face (``below``: its two faces, from their junctions
    down to ``stem_bottom_mm``, heights decreasing; the bottom face, fillets included, up to
    them)."""

    plate: PlateProfile
    stem: tuple[StemFace, StemFace]
    stem_top_mm: float
    below: tuple[StemFace, StemFace] | None = None
    stem_bottom_mm: float | None = None


def tee_profile(points: np.ndarray, normals: np.ndarray, frame: SectionFrame, *, roots_mm: dict[int, np.ndarray],
                stem_cut_mm: float, half_width_mm: float, bin_mm: float, smooth_mm: float,
                min_normal_cos: float = 0.5, roots_below_mm: dict[int, np.ndarray] | None = None) -> TeeProfile | None:
    """A T-joint's section (a stem on the base's top face, +y): the points within
    ``half_width_mm`` of the plane; ``roots_mm`` each stem face's root (x, y) in the section, by the
    side the base runs on from it (+1, -1: the fillets' measured roots). The base's bottom face
    from the points facing down, as ``plate_profile``; its top face from the points above the
    base's mid-plane and below each root's bisector (the 45 deg line from the root between base
    and stem), a median per bin of ``bin_mm`` along x, smoothed as ``plate_profile`` does; each
    stem face from the points above its bisector, a median x per bin of height, smoothed the same
    way, from where the top face's profile crosses the bisector up to ``stem_cut_mm`` above the
    root (the stem is cut there: no load reaches it in the base's tests). A cruciform's section
    (``roots_below_mm``: the lower stem's roots on the bottom face, by side as ``roots_mm``): its
    bottom face and lower stem read as the top face and stem are, mirrored (y -> -y); the base's
    mid-plane midway between the two faces' roots. None: a face or a stem has too few points."""
    if set(roots_mm) != {-1, 1}:
        raise ValueError(f"roots_mm must give the stem's two faces' roots (sides -1 and +1), got sides {sorted(roots_mm)}")
    if roots_below_mm is not None and set(roots_below_mm) != {-1, 1}:
        raise ValueError(f"roots_below_mm must give the lower stem's two faces' roots (sides -1 and +1), got sides "
                         f"{sorted(roots_below_mm)}")
    if half_width_mm <= 0 or bin_mm <= 0 or smooth_mm < 0 or stem_cut_mm <= 0:
        raise ValueError(f"half_width_mm, bin_mm and stem_cut_mm must be positive and smooth_mm not negative, got "
                         f"{half_width_mm}, {bin_mm}, {stem_cut_mm}, {smooth_mm}")
    xys = to_section(frame, points)
    slab = np.abs(xys[:, 2]) <= half_width_mm
    xys, facing = xys[slab], np.asarray(normals, np.float64)[slab] @ frame.up
    if len(xys) < 20:
        return None
    x, y = xys[:, 0], xys[:, 1]
    roots = {s: np.asarray(roots_mm[s], np.float64) for s in (-1, 1)}
    base_top = 0.5 * (roots[-1][1] + roots[1][1])
    x0 = np.floor(x.min() / bin_mm) * bin_mm
    edges = x0 + bin_mm * np.arange(int(np.ceil((x.max() - x0) / bin_mm)) + 2)
    centres = 0.5 * (edges[:-1] + edges[1:])
    half = smooth_mm / bin_mm
    if roots_below_mm is None:
        bottom, has_bottom = _face(x[facing < -min_normal_cos], y[facing < -min_normal_cos], edges)
        thickness_guess = base_top - np.nanmedian(bottom) if has_bottom.any() else np.nan
        if not np.isfinite(thickness_guess):
            return None
    else:  # the bottom face as a top face, mirrored
        below = {s: np.asarray(roots_below_mm[s], np.float64) * [1.0, -1.0] for s in (-1, 1)}
        thickness_guess = base_top + 0.5 * (below[-1][1] + below[1][1])
        bottom, has_bottom = _beside_stem(x, -y, below, thickness_guess, edges)
    top, has_top = _beside_stem(x, y, roots, thickness_guess, edges)
    if has_top.sum() < 10 or has_bottom.sum() < 10:
        return None
    lo = max(np.flatnonzero(has_top)[0], np.flatnonzero(has_bottom)[0])
    hi = min(np.flatnonzero(has_top)[-1], np.flatnonzero(has_bottom)[-1])
    top_filled = _filled_beside_stem(top, has_top, centres, roots, lo, hi, half)
    if roots_below_mm is None:
        bottom_filled = _filled_smoothed(bottom, has_bottom, lo, hi, half, -1.0)
    else:
        bottom_filled = _filled_beside_stem(bottom, has_bottom, centres, below, lo, hi, half)
    if top_filled is None or bottom_filled is None:
        return None
    stem_top = base_top + stem_cut_mm
    faces = _stem_faces(x, y, roots, top_filled, centres, stem_cut_mm, stem_top, bin_mm, half)
    if faces is None:
        return None
    if roots_below_mm is None:
        return TeeProfile(plate=PlateProfile(x_mm=centres, top_mm=top_filled, bottom_mm=bottom_filled,
                                             measured_top=has_top, measured_bottom=has_bottom),
                          stem=faces, stem_top_mm=float(stem_top))
    stem_bottom = 0.5 * (below[-1][1] + below[1][1]) + stem_cut_mm  # mirrored: the lower stem's cut, -y
    under = _stem_faces(x, -y, below, bottom_filled, centres, stem_cut_mm, stem_bottom, bin_mm, half)
    if under is None:
        return None
    under = tuple(replace(f, root_mm=f.root_mm * [1.0, -1.0], y_mm=-f.y_mm) for f in under)
    return TeeProfile(plate=PlateProfile(x_mm=centres, top_mm=top_filled, bottom_mm=-bottom_filled,
                                         measured_top=has_top, measured_bottom=has_bottom),
                      stem=faces, stem_top_mm=float(stem_top), below=(under[0], under[1]),
                      stem_bottom_mm=float(-stem_bottom))


def _beyond(x: np.ndarray, y: np.ndarray, roots: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
    """Per side, the points beyond the root's bisector on its side of the stem (the stem's)."""
    middle = 0.5 * (roots[-1][0] + roots[1][0])  # the stem's mid-plane
    return {s: (s * (x - middle) > 0) & (s * (x - roots[s][0]) < (y - roots[s][1])) for s in (-1, 1)}


def _beside_stem(x: np.ndarray, y: np.ndarray, roots: dict[int, np.ndarray], thickness_guess: float,
                 edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The top face's median y per bin (``_face``) beside a stem standing on it at ``roots``: the
    points above the base's mid-plane and below each root's bisector, not between the stem's faces."""
    base_top = 0.5 * (roots[-1][1] + roots[1][1])
    right, left = roots[1][0], roots[-1][0]
    above = _beyond(x, y, roots)
    on_stem_side = (x > left - 1.0) & (x < right + 1.0)  # between the stem's faces (its top end)
    top_points = (y > base_top - thickness_guess / 2) & ~above[-1] & ~above[1] & ~on_stem_side
    return _face(x[top_points], y[top_points], edges)


def _filled_beside_stem(top: np.ndarray, has_top: np.ndarray, centres: np.ndarray, roots: dict[int, np.ndarray],
                        lo: int, hi: int, half: float) -> np.ndarray | None:
    """The top face's heights on either side of the stem, each filled and smoothed on its own (the
    bins between the stem's faces are neither face's: NaN); None: a side has too few bins."""
    right, left = roots[1][0], roots[-1][0]
    top_filled = np.full(len(top), np.nan)
    for side_bins in (np.flatnonzero(centres < left), np.flatnonzero(centres > right)):
        side_bins = side_bins[(side_bins >= lo) & (side_bins <= hi)]
        if len(side_bins) < 10 or not has_top[side_bins].any():
            return None
        a, b = side_bins[0], side_bins[-1]
        top_filled[a:b + 1] = _filled_smoothed(top, has_top, a, b, half, 1.0)[a:b + 1]
    return top_filled


def _stem_faces(x: np.ndarray, y: np.ndarray, roots: dict[int, np.ndarray], top_filled: np.ndarray,
                centres: np.ndarray, stem_cut_mm: float, stem_top: float, bin_mm: float,
                half: float) -> tuple[StemFace, StemFace] | None:
    """The stem's two faces (+1, then -1) standing on the top face at ``roots``, cut at ``stem_top``
    (``stem_cut_mm`` over the base's face): each from where the top face's profile crosses its
    root's bisector, a median x per bin of height from the points beyond the bisector, filled and
    smoothed; None: too few points."""
    above = _beyond(x, y, roots)
    faces = []
    for s in (1, -1):
        root = roots[s]
        # where the top profile, from far out toward the root, first rises above the bisector
        bins = np.flatnonzero(np.isfinite(top_filled) & (s * (centres - root[0]) > 0))
        bins = bins[np.argsort(-s * centres[bins])]  # from far out inward
        crossed = bins[(top_filled[bins] - root[1]) >= s * (centres[bins] - root[0])]
        if len(crossed) == 0:
            return None
        j = crossed[0]
        junction = np.array([centres[j], top_filled[j]])
        sel = above[s] & (s * (x - root[0]) > -1.0) & (s * (x - root[0]) < stem_cut_mm) & (y <= stem_top + bin_mm)
        y_edges = junction[1] + bin_mm * np.arange(int(np.ceil((stem_top - junction[1]) / bin_mm)) + 2)
        face_x, has = _face(y[sel], x[sel], y_edges)
        if has.sum() < 10:
            return None
        # the junction first, then a median x per bin of height, filled and smoothed together
        heights = np.r_[junction[1], 0.5 * (y_edges[:-1] + y_edges[1:])]
        xs = _filled_smoothed(np.r_[junction[0], face_x], np.r_[True, has], 0, len(heights) - 1, half, float(s))
        keep = heights < stem_top
        faces.append(StemFace(side=s, root_mm=root, junction_x_mm=float(junction[0]),
                              y_mm=np.r_[heights[keep], stem_top], x_mm=np.r_[xs[keep], np.interp(stem_top, heights, xs)]))
    return faces[0], faces[1]


def tee_section(profile: TeeProfile, *, cut_mm: float, fine_mm: np.ndarray) -> PlaneSection:
    """A T-joint's outline (counter-clockwise): the base's bottom face left to right, the right
    cut, the top face right to left up to the right stem face's junction, up that face to the
    stem's cut, across, down the left face, the top face on to the left cut; ``cut_mm`` inside the
    range both base faces span; the corners kept, the elements finest at ``fine_mm``. A
    cruciform's bottom face (``profile.below``) likewise: left to right up to the lower stem's
    left face's junction, down it to the lower stem's cut, across, up its right face, on to the
    right cut."""
    plate = profile.plate
    both = np.isfinite(plate.bottom_mm)
    x_lo, x_hi = plate.x_mm[both][0] + cut_mm, plate.x_mm[both][-1] - cut_mm
    right, left = profile.stem
    stems = [profile.stem] + ([profile.below] if profile.below is not None else [])
    if not all(x_lo < lf.junction_x_mm and rf.junction_x_mm < x_hi for rf, lf in stems):
        raise ValueError(f"the section spans {x_hi - x_lo + 2 * cut_mm:.1f} mm: the stem's fillets are not "
                         f"{cut_mm:g} mm inside either end")
    top_ok = np.isfinite(plate.top_mm)

    def top_at(xs):
        return np.interp(xs, plate.x_mm[top_ok], plate.top_mm[top_ok])

    if profile.below is None:
        bx = np.r_[x_lo, plate.x_mm[(plate.x_mm > x_lo) & (plate.x_mm < x_hi)], x_hi]
        bottom = [np.c_[bx, np.interp(bx, plate.x_mm[both], plate.bottom_mm[both])]]
    else:
        low_right, low_left = profile.below

        def bottom_at(xs):
            return np.interp(xs, plate.x_mm[both], plate.bottom_mm[both])

        blx = np.r_[x_lo, plate.x_mm[(plate.x_mm > x_lo) & (plate.x_mm < low_left.junction_x_mm) & both]]
        brx = np.r_[plate.x_mm[(plate.x_mm > low_right.junction_x_mm) & (plate.x_mm < x_hi) & both], x_hi]
        bottom = [np.c_[blx, bottom_at(blx)], np.c_[low_left.x_mm, low_left.y_mm],
                  np.c_[low_right.x_mm, low_right.y_mm][::-1], np.c_[brx, bottom_at(brx)]]
    rx = np.r_[x_hi, plate.x_mm[(plate.x_mm < x_hi) & (plate.x_mm > right.junction_x_mm) & top_ok][::-1]]
    lx = np.r_[plate.x_mm[(plate.x_mm < left.junction_x_mm) & (plate.x_mm > x_lo) & top_ok][::-1], x_lo]
    parts = bottom + [np.c_[rx, top_at(rx)], np.c_[right.x_mm, right.y_mm], np.c_[left.x_mm, left.y_mm][::-1],
                      np.c_[lx, top_at(lx)]]
    outline = np.concatenate(parts)
    n = np.cumsum([len(p) for p in parts])
    if profile.below is None:
        corners = (0, n[0] - 1, n[0], n[2] - 1, n[2], n[4] - 1)
    else:  # the lower stem's cut's two ends too
        corners = (0, n[1] - 1, n[1], n[3] - 1, n[3], n[5] - 1, n[5], n[7] - 1)
    return PlaneSection(outline, fine_mm=np.asarray(fine_mm, np.float64).reshape(-1, 2), corners=corners)


def rounded_tee(profile: TeeProfile, radius_mm: float) -> TeeProfile:
    """A T-joint's section with every notch rounded to ``radius_mm`` at least (``rounded_notches``'
    rolling disk): the base's faces as a plate's (the base toes), each stem face as a face seen
    from its side, heights along the stem (the stem toes), the stem's cut left where it is; a
    cruciform's lower stem too."""
    if not radius_mm > 0:
        raise ValueError(f"radius_mm must be positive, got {radius_mm}")

    def rounded(stem: tuple[StemFace, StemFace]) -> tuple[StemFace, StemFace]:
        faces = []
        for face in stem:
            step = abs(float(np.median(np.diff(face.y_mm))))  # a lower stem's heights decrease
            # seen from its side (outward +side): the part lies at smaller side * x
            x = face.side * _closed_from_above(face.side * face.x_mm, step, radius_mm)
            faces.append(replace(face, x_mm=x))
        return faces[0], faces[1]

    return TeeProfile(plate=rounded_notches(profile.plate, radius_mm), stem=rounded(profile.stem),
                      stem_top_mm=profile.stem_top_mm, below=None if profile.below is None else rounded(profile.below),
                      stem_bottom_mm=profile.stem_bottom_mm)


def _rounded_corner(corner: np.ndarray, e1: np.ndarray, e2: np.ndarray, radius_mm: float, step_mm: float) -> np.ndarray:
    """The points of an arc of ``radius_mm`` rounding the corner where a path heading ``e1`` (unit)
    turns to ``e2``, tangent to both, about ``step_mm`` apart (its ends included)."""
    turn = float(np.arccos(np.clip(e1 @ e2, -1.0, 1.0)))
    d = radius_mm * np.tan(turn / 2)
    start, end = corner - d * e1, corner + d * e2
    normal = np.sign(e1[0] * e2[1] - e1[1] * e2[0]) * np.array([-e1[1], e1[0]])
    centre = start + radius_mm * normal
    a0, a1 = (np.arctan2(*(p - centre)[::-1]) for p in (start, end))
    sweep = (a1 - a0 + np.pi) % (2 * np.pi) - np.pi
    t = a0 + sweep * np.linspace(0.0, 1.0, max(3, int(np.ceil(abs(sweep) * radius_mm / step_mm)) + 1))
    return centre + radius_mm * np.c_[np.cos(t), np.sin(t)]


def _evenly(path: np.ndarray, step_mm: float) -> np.ndarray:
    """The open polyline ``path`` with points added on each stretch longer than ``step_mm``, evenly."""
    out = [path[:1]]
    for p, q in zip(path[:-1], path[1:]):
        n = max(1, int(np.ceil(np.linalg.norm(q - p) / step_mm)))
        out.append(p + (q - p) * (np.arange(1, n + 1) / n)[:, None])
    return np.concatenate(out)


def drawn_tee_section(*, base_thickness_mm: float, stem_thickness_mm: float, legs: dict[int, tuple[float, float]],
                      half_length_mm: float, stem_cut_mm: float, radius_mm: float, step_mm: float,
                      legs_below: dict[int, tuple[float, float]] | None = None) -> PlaneSection:
    """The drawn (idealised) section of a T-joint: a base plate of ``base_thickness_mm`` (faces at
    +-thickness/2, ``half_length_mm`` either side of the stem's mid-plane x = 0), a stem of
    ``stem_thickness_mm`` standing on its top face, cut ``stem_cut_mm`` above it, and on each side
    (``legs``: +1 / -1 -> (leg on the base, leg on the stem), mm) a fillet with a straight face, each
    toe rounded to ``radius_mm``; the outline's points about ``step_mm`` apart along the face and
    the toes, its corners kept, the elements finest at the four toes (base +1, base -1, stem +1,
    stem -1). A cruciform's (``legs_below``: the lower stem's fillets, by side as ``legs``): the
    same stem and fillets on the bottom face, mirrored (y -> -y), their four toes after the upper
    ones in the same order."""
    if not (base_thickness_mm > 0 and stem_thickness_mm > 0 and half_length_mm > 0 and stem_cut_mm > 0
            and radius_mm > 0 and step_mm > 0):
        raise ValueError("the T-joint's thicknesses, half length, stem cut, radius and step must be positive")
    for name, given in (("legs", legs), ("legs_below", legs_below)):
        if given is not None and (set(given) != {-1, 1} or min(min(v) for v in given.values()) <= 0):
            raise ValueError(f"{name} must give both fillets' (base, stem) legs, positive, got {given}")
    x0, z0 = stem_thickness_mm / 2, base_thickness_mm / 2

    def stem_path(legs: dict[int, tuple[float, float]]) -> tuple[np.ndarray, np.ndarray]:
        """The top face's path from (half_length, z0) up the stem, and from its other face down to
        (-half_length, z0), each ``step_mm`` apart."""
        halves = {}
        for side in (1, -1):
            a, b = legs[side]
            B, S = np.array([x0 + a, z0]), np.array([x0, z0 + b])
            face = (S - B) / np.linalg.norm(S - B)
            path = np.concatenate([_rounded_corner(B, np.array([-1.0, 0.0]), face, radius_mm, step_mm),
                                   _rounded_corner(S, face, np.array([0.0, 1.0]), radius_mm, step_mm)])
            halves[side] = np.r_[[[half_length_mm, z0]], path, [[x0, z0 + stem_cut_mm]]] * [side, 1.0]
        # every straight stretch in points ``step_mm`` apart too (the mesher's splines through points
        # spaced unevenly overshoot), the corners' places kept
        return _evenly(halves[1], step_mm), _evenly(halves[-1][::-1], step_mm)

    def toes_of(legs: dict[int, tuple[float, float]], face: float) -> list[np.ndarray]:
        return [np.array([side * (x0 + legs[side][0]), face * z0]) for side in (1, -1)] + \
            [np.array([side * x0, face * (z0 + legs[side][1])]) for side in (1, -1)]

    right, left = stem_path(legs)
    if legs_below is None:
        bottom = [_evenly(np.array([[-half_length_mm, -z0], [half_length_mm, -z0]]), step_mm)]
    else:  # the upper path mirrored: from (-half_length, -z0) down the lower stem's x < 0 face, up its other
        low_right, low_left = (p * [1.0, -1.0] for p in stem_path(legs_below))
        bottom = [low_left[::-1], _evenly(np.r_[low_left[:1], low_right[-1:]], step_mm)[1:-1], low_right[::-1]]
    parts = bottom + [_evenly(np.r_[bottom[-1][-1:], right[:1]], step_mm)[1:-1], right,
                      _evenly(np.r_[right[-1:], left[:1]], step_mm)[1:-1], left,
                      _evenly(np.r_[left[-1:], bottom[0][:1]], step_mm)[1:-1]]
    outline = np.concatenate(parts)
    starts = np.cumsum([0] + [len(p) for p in parts])
    if legs_below is None:
        corners = tuple(int(k) for k in (0, starts[1] - 1, starts[2], starts[3] - 1, starts[4], starts[5] - 1))
    else:
        corners = tuple(int(k) for k in (0, starts[1] - 1, starts[2], starts[3] - 1, starts[4], starts[5] - 1,
                                          starts[6], starts[7] - 1))
    toes = toes_of(legs, 1.0) + ([] if legs_below is None else toes_of(legs_below, -1.0))
    return PlaneSection(outline, fine_mm=np.array(toes), corners=corners)
