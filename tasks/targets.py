"""Sticker targets: circles in a pass's intensity image, refined to 3-D centres.

1. The intensity grid (profiles x columns) is resampled to square pixels of the pass's own
   point spacing and searched with OpenCV's Hough transform for circles of about the sticker's
   radius (the paper's method; ``find_circles``).
2. Each circle is refined in 3-D with the organized points (the pixel -> 3-D "dictionary"): the
   sticker's bright points give its plane; the sticker's edge is located to sub-pixel precision on
   each bright/dark grid edge, and a circle of the known radius is fitted to the edge points found
   along the profiles (least squares). Along a profile each point's intensity integrates its camera
   pixel, as wide as the point spacing, so the pixel the rim crosses reads its share of sticker:
   the rim point is where the intensity crosses halfway between sticker and steel between the two
   neighbours across the rim, or (``rim_edge`` "share") their shares' sum of a pixel from the
   sticker side's far boundary (``_edge_points``; the halfway crossing is off by up to 0.09 of the
   spacing, RMS 0.06, with where the rim falls in its pixel). Across profiles the laser line (about
   0.1 mm thick) is narrower than the profile spacing (0.1-0.5 mm), so neighbours read all sticker
   or all metal and the crossing is only known to within the spacing. Those edges count for the
   rim's coverage, not the fit (on the demo sample, in-plane centre error median 18.7 -> 5.2 um,
   RMS 20.1 -> 8.4 um; at the paper's resolution median 1.2 -> 0.7 um, RMS 3.1 -> 1.6 um). The
   shares instead of the halfway crossing (the default since 2026-11-29,
   ``schemas.reconstruction.TargetsConfig.rim_edge``; against the simulator's true stickers, 3-D
   centre error median: demo 9.9 -> 7.3 um, ci 8.6 -> 5.5 um; bench/README.md, the targets' sigma).
   The paper has an edge (about 0.1 mm high). Seen obliquely, the rays that last meet paper on
   the far side graze the top's rim, but on the side facing the sensor they run into the edge and
   the last of them grazes its foot, one edge height below the top: where the rays cross the top's
   plane, that side of the rim lies farther out by the edge height times the tangent of the view
   (60 um at 50 deg). The fit takes the edge height as a third unknown, moving the facing side's
   rim points along their own rays (``_fit_rim``). Its covariance gives the height's own sigma and
   how far the centre moves per mm of height along the fit's valley: ``tasks.target_weights``
   weighs a centre whose height is off its sample's by what that move makes of it.
3. A quality figure per target: edge-fit RMS, the share of the rim that was seen, the radius a
   free fit finds. Circles cut by the pass border, shadows or glare fail these checks.

The steps also run on a pass fed profile block by profile block, in memory that does not grow
with the pass (a stage never holds a whole pass): the search of ``tasks.target_search``
(``GridSpacing``, ``search_grid``, ``HoughImage``, ``find_circles``), then ``refine_target`` on
each circle's window (``SearchGrid.window``) alone. ``detect_targets`` runs the same steps on a whole pass; the
results are the same bytes however the pass is split into blocks.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import get_args

import cv2
import numpy as np
from scipy.optimize import least_squares

from schemas.reconstruction import RimEdge
from tasks.arrays import distinct
from tasks.target_search import GridSpacing, HoughImage, SearchGrid, find_circles, search_grid

__all__ = ["RIM_EDGES", "Target", "TargetDetection", "TargetRefinement", "SearchGrid", "GridSpacing", "HoughImage",
           "search_grid", "find_circles", "refine_target", "detect_targets"]

RIM_EDGES = get_args(RimEdge)
_RIM_BINS = 24
_REJECTIONS = ("rim", "fit", "radius", "points")


@dataclass(frozen=True)
class Target:
    """A sticker's centre on its top surface, in the frame of the input points (mm)."""

    centre_mm: np.ndarray  # (3,)
    normal: np.ndarray  # (3,) unit, toward the sensor side
    pixel: tuple[float, float]  # (profile, column) of the Hough circle
    rms_mm: float  # the fitted edge points' (along the profiles) distance to the circle
    rim_coverage: float  # share of the rim's angular bins holding edge points
    free_radius_mm: float  # radius of an unconstrained circle fit
    n_edge_points: int  # edge points fitted
    edge_height_mm: float  # the sticker edge's height the fit found (0 without sensor origins)
    edge_height_sigma_mm: float  # that height's 1-sigma from the fit's own covariance (0: none fitted)
    centre_per_height: np.ndarray  # (3,) mm of centre per mm of height along the fit's valley (in the plane)


@dataclass(frozen=True)
class TargetRefinement:
    """One Hough circle refined: its ``target``, or why it was rejected (``rejected``: one of
    "rim", "fit", "radius", "points"), the other one None."""

    target: Target | None
    rejected: str | None


@dataclass(frozen=True)
class TargetDetection:
    targets: list[Target]
    n_circles: int  # Hough candidates before refinement
    rejected: dict[str, int]  # reason -> count
    pixel_mm: float  # square pixel size the search ran at

    @classmethod
    def from_refinements(cls, refinements: list[TargetRefinement], *, pixel_mm: float) -> TargetDetection:
        """The detection of a pass from its circles' refinements, in the circles' order."""
        rejected = dict.fromkeys(_REJECTIONS, 0)
        for r in refinements:
            if r.rejected is not None:
                rejected[r.rejected] += 1
        return cls(targets=[r.target for r in refinements if r.target is not None], n_circles=len(refinements),
                   rejected=rejected, pixel_mm=pixel_mm)


def _threshold(intensity: np.ndarray) -> float:
    values = intensity[intensity > 0]
    if values.size == 0:
        return float("inf")
    img = np.clip(values / 4, 0, 255).astype(np.uint8).reshape(-1, 1)
    t, _ = cv2.threshold(img, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    return float(t) * 4


def _plane(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    return c, vt[2]


def _on_plane(points: np.ndarray, origins: np.ndarray, plane_point: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Where each point's ray from its sensor origin crosses the plane."""
    ray = points - origins
    t = ((plane_point - origins) @ normal) / np.where(np.abs(ray @ normal) > 1e-12, ray @ normal, 1e-12)
    return origins + t[..., None] * ray


def _plateau(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """A plane a + b*row + c*col fitted to ``values`` where ``mask`` (2-D), evaluated everywhere;
    the median where too few points say otherwise."""
    rows, cols = np.nonzero(mask)
    if len(rows) < 12:
        return np.full(values.shape, np.median(values[mask]) if mask.any() else np.nan)
    A = np.column_stack([np.ones(len(rows)), rows, cols])
    coef, *_ = np.linalg.lstsq(A, values[mask].astype(np.float64), rcond=None)
    r, c = np.indices(values.shape)
    return coef[0] + coef[1] * r + coef[2] * c


def _edge_levels(local: np.ndarray, bright: np.ndarray, near: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, the intensity of the sticker and of the metal, each a plane over the window: the
    light falls off with distance and angle across an obliquely seen sticker, and one level for all
    of it would move the near rim out and the far rim in. ``near``: the pixels close enough to the
    sticker to serve (other faces in the window are lit otherwise)."""
    valid = (local > 0) & near
    pad_b = np.pad(bright, 1, mode="edge")
    interior = bright.copy()
    exterior = ~bright & valid
    for dr, dc in ((0, 1), (2, 1), (1, 0), (1, 2)):  # away from the rim: all four neighbours alike
        shifted = pad_b[dr:dr + bright.shape[0], dc:dc + bright.shape[1]]
        interior &= shifted
        exterior &= ~shifted
    return _plateau(local, interior & valid), _plateau(local, exterior)


def _edge_points(intensity: np.ndarray, points: np.ndarray, bright: np.ndarray, sticker: np.ndarray,
                 metal: np.ndarray, rim_edge: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sub-pixel edge points (k, 3) where bright and dark grid neighbours meet, from the intensity
    between ``sticker`` and ``metal`` (each per pixel). All (rows, columns) grids of one window.
    Also (k,) bool: True for an edge between neighbours along a profile (columns), False across
    profiles (rows); and (k,) int, the row (profile) of each edge's first neighbour.

    Along a profile (``rim_edge``): "halfway", where the intensity crosses halfway between the
    two, interpolated between the two pixels' centres; "share", each pixel integrates its share
    of sticker (the module's notes), so the edge lies the two shares' sum of a pixel from the
    sticker side's far boundary (halfway is off by up to 0.09 of the spacing, RMS 0.06, with where
    the edge falls in its pixel). Across profiles the laser line is thinner than the spacing:
    halfway, as a bound."""
    if rim_edge == "share":
        span = sticker - metal
        share = np.clip((intensity.astype(np.float64) - metal) / np.where(np.abs(span) > 1e-9, span, 1e-9), 0.0, 1.0)
    level = 0.5 * (sticker + metal)
    I = intensity.astype(np.float64) - level
    P = points
    B = bright
    valid = np.isfinite(P).all(axis=-1) & (intensity > 0)
    out, along, rows = [], [], []
    for axis in (0, 1):
        a = [slice(None), slice(None)]
        b = [slice(None), slice(None)]
        a[axis], b[axis] = slice(None, -1), slice(1, None)
        a, b = tuple(a), tuple(b)
        pair = valid[a] & valid[b] & (B[a] != B[b])
        if not pair.any():
            continue
        pa, pb = P[a][pair], P[b][pair]
        if axis == 1 and rim_edge == "share":
            total = share[a][pair] + share[b][pair]
            # from the midpoint toward b: sticker at a, the edge (total - 1) of a pixel on; at b, (1 - total)
            f = 0.5 + np.clip(np.where(B[a][pair], total - 1.0, 1.0 - total), -0.5, 0.5)
        else:
            ia, ib = I[a][pair], I[b][pair]
            f = np.clip(ia / np.where(ia != ib, ia - ib, 1.0), 0.0, 1.0)
        out.append(pa + f[:, None] * (pb - pa))
        along.append(np.full(len(f), axis == 1))
        rows.append(np.nonzero(pair)[0])
    if not out:
        return np.zeros((0, 3)), np.zeros(0, bool), np.zeros(0, np.int64)
    return np.concatenate(out), np.concatenate(along), np.concatenate(rows)


def _fit_circle(uv: np.ndarray, radius: float | None) -> tuple[np.ndarray, float, float]:
    """Centre (2,), radius and RMS of a circle fit in the plane; radius fixed when given."""
    A = np.column_stack([2 * uv, np.ones(len(uv))])
    sol, *_ = np.linalg.lstsq(A, (uv**2).sum(axis=1), rcond=None)
    centre0 = sol[:2]
    r0 = float(np.sqrt(max(sol[2] + centre0 @ centre0, 1e-12)))
    if radius is None:
        fun = lambda q: np.linalg.norm(uv - q[:2], axis=1) - q[2]  # noqa: E731
        q = least_squares(fun, np.append(centre0, r0)).x
        centre, r = q[:2], float(q[2])
    else:
        fun = lambda q: np.linalg.norm(uv - q, axis=1) - radius  # noqa: E731
        centre, r = least_squares(fun, centre0, loss="soft_l1", f_scale=0.05).x, radius
    rms = float(np.sqrt(np.mean((np.linalg.norm(uv - centre, axis=1) - r) ** 2)))
    return centre, r, rms


_MAX_EDGE_MM = 0.3  # the highest sticker edge the fit may find (paper ~0.1 mm, vinyl ~0.2 mm)


def _fit_rim(uv: np.ndarray, travel: np.ndarray, radius: float) -> tuple[np.ndarray, float, np.ndarray, np.ndarray]:
    """A circle of ``radius`` fitted to rim points ``uv`` (k, 2), found where their rays cross the
    sticker's top plane, with the sticker edge's height as a third unknown (the module's notes):
    a point on the side facing the sensor (its ray travels inward) truly lies where its ray, going
    on, has dropped that height, ``travel`` (k, 2) per mm of drop. Returns the centre (2,), the
    height (0 .. ``_MAX_EDGE_MM``), the points moved onto the rim (k, 2) and the fit's covariance
    of (centre u, centre v, height) (3, 3): the residuals' variance times the inverse of the
    Gauss-Newton Hessian at the solution."""
    centre, _, _ = _fit_circle(uv, radius)
    facing = np.einsum("ij,ij->i", uv - centre, travel) < 0
    shift = np.where(facing[:, None], travel, 0.0)
    fun = lambda q: np.linalg.norm(uv + q[2] * shift - q[:2], axis=1) - radius  # noqa: E731
    fit = least_squares(fun, np.append(centre, 0.5 * _MAX_EDGE_MM), bounds=([-np.inf, -np.inf, 0.0],
                        [np.inf, np.inf, _MAX_EDGE_MM]), loss="soft_l1", f_scale=0.05)
    q = fit.x
    dof = max(len(uv) - 3, 1)
    variance = float(fit.fun @ fit.fun) / dof
    cov = variance * np.linalg.pinv(fit.jac.T @ fit.jac)
    return q[:2], float(q[2]), uv + q[2] * shift, cov


def refine_target(intensity: np.ndarray, points_mm: np.ndarray, sensor_origins_mm: np.ndarray | None, *,
                  pixel: tuple[float, float], grid: SearchGrid, max_rms_mm: float, min_rim_coverage: float,
                  radius_tolerance: float, rim_edge: str) -> TargetRefinement:
    """Refine one Hough circle to a target from its window of the pass alone (``grid.window``).

    intensity : (rows, columns) uint16, the window's intensity, 0 where nothing was returned.
    points_mm : (rows, columns, 3) float, mm, the window's organized points (NaN missing).
    sensor_origins_mm : (rows, 3) float, mm, the sensor origin of each of the window's profiles, or
        None (see ``detect_targets``).
    pixel : (profile, column) of the circle in the pass (``grid.grid_position``), recorded.
    grid : the pass's search (``search_grid``): the sticker's radius and the point spacing.
    max_rms_mm, min_rim_coverage, radius_tolerance, rim_edge : as ``detect_targets``.
    """
    # Own copies: every operation below sees the same array layout whether the window was cut from
    # a whole pass or from a block of it, so the result is the same bytes.
    local = np.array(intensity)
    points = np.array(points_mm, dtype=np.float64)
    origins = None if sensor_origins_mm is None else np.array(sensor_origins_mm, dtype=np.float64)
    if local.ndim != 2 or points.shape != local.shape + (3,):
        raise ValueError(f"intensity (rows, columns) and points (rows, columns, 3) must match, "
                         f"got {local.shape} and {points.shape}")
    if rim_edge not in RIM_EDGES:
        raise ValueError(f"rim_edge must be one of {', '.join(RIM_EDGES)}, got {rim_edge!r}")
    if origins is not None and origins.shape != (local.shape[0], 3):
        raise ValueError(f"sensor_origins_mm must have shape ({local.shape[0]}, 3), got {origins.shape}")
    radius = grid.radius_mm
    split = _threshold(local)  # sticker vs its own surroundings
    bright = local >= split
    finite = np.isfinite(points).all(axis=-1)
    blob = points[bright & finite]
    close = np.linalg.norm(points - (blob.mean(axis=0) if len(blob) else 0.0), axis=-1) < 1.5 * radius
    sticker, metal = _edge_levels(local, bright, close)
    if not (np.isfinite(sticker).all() and np.isfinite(metal).all()):  # too few pixels for a plane
        dark = ~bright & (local > 0)
        if rim_edge == "share" and bright.any() and dark.any():
            sticker, metal = (np.full(local.shape, float(np.median(local[m]))) for m in (bright, dark))
        else:  # halfway: the threshold itself
            sticker = metal = np.full(local.shape, float(split))
    inside = bright & finite
    if np.count_nonzero(inside) < 12:
        return TargetRefinement(None, "points")
    # Twice: the plane of all bright points first; then of those well inside the rim only
    # (rim points read bright while their 3-D point lies on the metal, 0.1 mm lower, which
    # tilts and lowers the plane and, at oblique views, shifts every rim ray the same way).
    plane_points = points[inside]
    for attempt in range(2):
        origin, normal = _plane(plane_points)
        side = origins.mean(axis=0) if origins is not None else origin + np.array([0.0, 0.0, 1.0])
        if normal @ (side - origin) < 0:
            normal = -normal
        on_plane = points if origins is None else _on_plane(points, origins[:, None, :], origin, normal)
        edges, along_profile, edge_rows = _edge_points(local, on_plane, bright, sticker, metal, rim_edge)
        if len(edges) < 12:
            break
        e1 = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(normal, e1)
        uv = np.column_stack([(edges - origin) @ e1, (edges - origin) @ e2])
        # keep edge points near the rim of the circle suggested by the bright blob; fit those
        # found along the profiles (the module's notes), count them all for the rim's coverage
        near = np.abs(np.linalg.norm(uv, axis=1) - radius) < 0.35 * radius
        rim_uv = uv[near]
        fitted = near & along_profile
        uv = uv[fitted]
        if len(uv) < 12:
            break
        if origins is None:
            centre_uv, _, _ = _fit_circle(uv, radius)
            edge_mm, cov = 0.0, None
        else:
            ray = edges[fitted] - origins[edge_rows[fitted]]
            drop = -(ray @ normal)  # the normal faces the sensor: rays go down it
            travel = np.column_stack([ray @ e1, ray @ e2]) / np.maximum(drop, 1e-9)[:, None]
            centre_uv, edge_mm, uv, cov = _fit_rim(uv, travel, radius)
        rms = float(np.sqrt(np.mean((np.linalg.norm(uv - centre_uv, axis=1) - radius) ** 2)))
        if attempt == 0:
            centre = origin + centre_uv[0] * e1 + centre_uv[1] * e2
            candidates = points[inside]
            radial = candidates - centre
            radial -= np.outer(radial @ normal, normal)
            core = np.linalg.norm(radial, axis=1) < 0.75 * radius
            if core.sum() < 12:
                break
            plane_points = candidates[core]
    if len(edges) < 12 or len(uv) < 12:
        return TargetRefinement(None, "points")
    _, free_r, _ = _fit_circle(uv, None)
    angles = np.arctan2(rim_uv[:, 1] - centre_uv[1], rim_uv[:, 0] - centre_uv[0])
    coverage = distinct(((angles + np.pi) / (2 * np.pi) * _RIM_BINS).astype(int) % _RIM_BINS).size / _RIM_BINS
    if coverage < min_rim_coverage:
        return TargetRefinement(None, "rim")
    if rms > max(max_rms_mm, 0.45 * max(grid.spacing_mm)):  # edges are quantised to the grid
        return TargetRefinement(None, "fit")
    if abs(free_r - radius) > radius_tolerance * radius:
        return TargetRefinement(None, "radius")
    centre = origin + centre_uv[0] * e1 + centre_uv[1] * e2
    if cov is None or not cov[2, 2] > 0:  # no height fitted (or none it could move)
        height_sigma, per_height = 0.0, np.zeros(3)
    else:
        height_sigma = float(np.sqrt(cov[2, 2]))
        slope = cov[:2, 2] / cov[2, 2]  # the centre's move per mm of height along the fit's valley
        per_height = slope[0] * e1 + slope[1] * e2
    return TargetRefinement(Target(centre_mm=centre, normal=normal, pixel=(float(pixel[0]), float(pixel[1])),
                                   rms_mm=rms, rim_coverage=float(coverage), free_radius_mm=float(free_r),
                                   n_edge_points=len(uv), edge_height_mm=edge_mm, edge_height_sigma_mm=height_sigma,
                                   centre_per_height=per_height), None)


def detect_targets(intensity: np.ndarray, points_mm: np.ndarray, *, sticker_diameter_mm: float,
                   sensor_origins_mm: np.ndarray | None = None, max_rms_mm: float,
                   min_rim_coverage: float, radius_tolerance: float, rim_edge: str) -> TargetDetection:
    """Find sticker targets in one whole pass (the steps a stage streams, run at once: the same
    result as any block-wise run).

    intensity : (profiles, columns) uint16, 0 where nothing was returned.
    points_mm : (profiles, columns, 3) float, mm, organized points of the same pass (NaN missing).
    sticker_diameter_mm : the stickers' nominal diameter.
    sensor_origins_mm : (profiles, 3) the sensor (laser) origin of each profile, same frame. With
        it, every rim point is taken where its own ray crosses the sticker's plane (the paper is
        0.1 mm proud of the steel, which matters at oblique views) and normals face the sensor;
        without it normals face +z.
    max_rms_mm : largest edge-fit RMS accepted, or 0.45 of the point spacing if that is larger
        (a point-sampled edge is only known to within one spacing).
    min_rim_coverage : least share of the rim's angular bins that must hold edge points (0..1);
        stickers cut by the pass border, shadows or glare fall short.
    radius_tolerance : largest relative difference between a free circle fit's radius and the
        nominal one.
    rim_edge : how a rim point is located along a profile (``RIM_EDGES``, ``_edge_points``):
        "halfway" where the intensity crosses halfway between sticker and metal, "share" from the
        two pixels' shares of sticker.
    The three thresholds and ``rim_edge`` have no defaults here: they come from ``schemas.reconstruction.TargetsConfig``.
    Targets come in the order ``find_circles`` ranks their circles.
    """
    intensity = np.asarray(intensity)
    points = np.asarray(points_mm, dtype=np.float64)
    if intensity.ndim != 2 or points.shape != intensity.shape + (3,):
        raise ValueError(f"intensity (profiles, columns) and points (profiles, columns, 3) must match, "
                         f"got {intensity.shape} and {points.shape}")
    if not sticker_diameter_mm > 0:
        raise ValueError(f"sticker_diameter_mm must be positive, got {sticker_diameter_mm}")
    origins = None if sensor_origins_mm is None else np.asarray(sensor_origins_mm, dtype=np.float64)
    if origins is not None and origins.shape != (intensity.shape[0], 3):
        raise ValueError(f"sensor_origins_mm must have shape ({intensity.shape[0]}, 3), got {origins.shape}")
    spacing = GridSpacing(intensity.shape[0])
    spacing.add(points, start=0)
    grid = search_grid(intensity.shape, spacing.spacing_mm(), sticker_diameter_mm=sticker_diameter_mm)
    if grid is None:
        return TargetDetection.from_refinements([], pixel_mm=float("nan"))
    image = HoughImage(grid)
    image.add(intensity)
    refinements = []
    for circle in find_circles(image.image(), radius_px=grid.radius_px):
        row, col = grid.grid_position(circle)
        window = grid.window(row, col)
        refinements.append(refine_target(intensity[window], points[window],
                                         None if origins is None else origins[window[0]], pixel=(row, col),
                                         grid=grid, max_rms_mm=max_rms_mm, min_rim_coverage=min_rim_coverage,
                                         radius_tolerance=radius_tolerance, rim_edge=rim_edge))
    return TargetDetection.from_refinements(refinements, pixel_mm=grid.pixel_mm)
