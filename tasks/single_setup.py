"""A single setup (the part never turned): tell the part from the fixture without a second setup.

With two setups the part is what moved between them: the stickers seen in both are the part's,
and the components that hold them are kept (``tasks.segment``). With one setup nothing moved, so
three other pieces of evidence decide, in this order:

1. **The fixture's plane.** The table the part stands on is the lowest plane, perpendicular to
   the cell's up direction, that holds a large share of the upward-facing points: found on a
   histogram of their heights, then fitted (least squares) to the points near it. Every point
   within ``plane_clearance_mm`` of it, or below it, goes; what stood on the table (the part,
   blocks, rails) comes apart from it.
2. **The part's drawing where the setup puts it.** When the setup states the part's nominal
   placement, the points outside the drawing's bounding box placed there go: rails and blocks
   beside or under the part. The box is grown by the placement tolerance and a margin across, and
   by ``plane_clearance_mm`` only on the face toward the fixture (the part rests on it: the
   supports under it go).
3. **One body of the part's size.** The largest remaining component (by points) is the part. Its
   extents along its principal axes must match the drawing's box: the longest within
   ``size_tolerance`` of the box's longest edge, the second within it of the second (from below,
   the scans may miss some of the part: ``min_seen_fraction``). Otherwise
   :class:`PartNotFound` names the figures: a silently wrong part is never kept.

The part's underside, on the fixture, is never seen: Poisson would leave it open (the surface runs
out to its bounding cube). ``fill_underside`` closes it with a plane at the lowest measured height,
over the part's outline seen from above; those points are marked as not measured.

Deterministic: histograms, least squares and a symmetric eigen-decomposition, no random draws.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scipy.ndimage import binary_fill_holes

from tasks.checks import check_points
from tasks.segment import keep_specimen_components

__all__ = ["FixturePlane", "PartNotFound", "SingleSetupResult", "Underside", "find_fixture_plane",
           "keep_part_single_setup", "fill_underside", "principal_extents_mm", "inside_drawing_box"]


class PartNotFound(ValueError):
    """The evidence of a single setup does not single out one body of the part's size."""


@dataclass(frozen=True)
class FixturePlane:
    """``normal`` (3,) unit, toward the part (up); ``offset_mm``: the plane is ``normal . p =
    offset_mm``; ``support``: upward-facing points within one bin of it; ``rms_mm``: their
    distance to the fitted plane, RMS."""

    normal: np.ndarray
    offset_mm: float
    support: int
    rms_mm: float


@dataclass(frozen=True)
class SingleSetupResult:
    """``keep`` (n,) bool: the part's points. ``plane``: the fixture plane removed (or None when
    none was found); ``below_plane``: points removed with it; ``outside_box``: points removed
    outside the placed drawing box (0 without a nominal placement); ``n_components``: components
    of what remained; ``kept_points``; ``extents_mm`` (3,) the kept body's extents along its
    principal axes, descending; ``expected_mm`` (3,) the drawing box's edges, descending."""

    keep: np.ndarray
    plane: FixturePlane | None
    below_plane: int
    outside_box: int
    n_components: int
    kept_points: int
    extents_mm: np.ndarray
    expected_mm: np.ndarray


def _unit(name: str, v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64).reshape(-1)
    if v.shape != (3,) or not np.isfinite(v).all() or np.linalg.norm(v) == 0:
        raise ValueError(f"{name} must be a finite non-zero 3-vector, got {v}")
    return v / np.linalg.norm(v)


def find_fixture_plane(points_mm: np.ndarray, normals: np.ndarray, *, up, max_tilt_deg: float = 10.0,
                       bin_mm: float = 0.5, min_share: float = 0.25) -> FixturePlane | None:
    """The lowest large plane facing ``up``.

    points_mm : (n, 3) float, mm, finite; normals : (n, 3) float, unit where finite (NaN rows are
    ignored), oriented toward the sensor; up : (3,) the cell's up direction in the points' frame.
    A height bin (``bin_mm`` along ``up``) of the upward-facing points (normal within
    ``max_tilt_deg`` of up) is a candidate when it holds at least ``min_share`` of the fullest
    bin's count and is a local maximum; the lowest candidate is the plane. None when no point faces
    up.
    """
    points = check_points("points_mm", points_mm)
    normals = np.asarray(normals, dtype=np.float64)
    if normals.shape != points.shape:
        raise ValueError(f"normals must have the points' shape {points.shape}, got {normals.shape}")
    up = _unit("up", up)
    facing = np.isfinite(normals).all(axis=1)
    facing[facing] = normals[facing] @ up >= np.cos(np.radians(max_tilt_deg))
    if not facing.any():
        return None
    heights = points[facing] @ up
    low = np.floor(heights.min() / bin_mm)
    index = (np.floor(heights / bin_mm) - low).astype(np.int64)
    counts = np.bincount(index)
    padded = np.concatenate([[0], counts, [0]])
    peak = (counts >= min_share * counts.max()) & (counts >= padded[:-2]) & (counts >= padded[2:])
    first = int(np.flatnonzero(peak)[0])
    facing_points = points[facing]
    near = np.abs(index - first) <= 1
    for _ in range(3):  # fit, then gather the upward-facing points within a bin of the fitted plane: a
        on = facing_points[near]  # table tilted against ``up`` spreads over several bins
        centre = on.mean(axis=0)
        _, vectors = np.linalg.eigh(np.cov((on - centre).T))  # least squares: the smallest principal axis
        normal = vectors[:, 0] * (1.0 if vectors[:, 0] @ up >= 0 else -1.0)
        offset = float(normal @ centre)
        near = np.abs(facing_points @ normal - offset) <= bin_mm
    rms = float(np.sqrt(np.mean((on @ normal - offset) ** 2)))
    return FixturePlane(normal=normal, offset_mm=offset, support=int(len(on)), rms_mm=rms)


def principal_extents_mm(points: np.ndarray, *, max_points: int = 1_000_000) -> np.ndarray:
    """(3,) a body's extents along its principal axes, descending, mm, from every k-th of its points
    (n, 3) (at most ``max_points``: deterministic)."""
    points = np.asarray(points, dtype=np.float64)[:: max(1, -(-len(points) // max_points))]
    if len(points) < 3:
        return np.zeros(3)
    return _principal_extents(points)


def _principal_extents(points: np.ndarray) -> np.ndarray:
    centre = points.mean(axis=0)
    _, vectors = np.linalg.eigh(np.cov((points - centre).T))
    along = (points - centre) @ vectors
    return np.sort(along.max(axis=0) - along.min(axis=0))[::-1]


def inside_drawing_box(points_mm: np.ndarray, *, T_frame_part, part_bounds_mm: tuple, grow_lo_mm,
                       grow_hi_mm) -> np.ndarray:
    """(n,) bool: the points (n, 3) mm inside the part's drawing box ``part_bounds_mm`` ((x0, y0, z0),
    (x1, y1, z1)) mm, specimen frame, placed by ``T_frame_part`` (4, 4) into the points' frame and
    grown by ``grow_lo_mm`` (3,) below its min corner and ``grow_hi_mm`` (3,) beyond its max corner."""
    points = check_points("points_mm", points_mm)
    T = np.asarray(T_frame_part, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ValueError(f"T_frame_part must be a finite (4, 4) pose, got shape {T.shape}")
    lo, hi = (np.asarray(b, dtype=np.float64) for b in part_bounds_mm)
    local = (points - T[:3, 3]) @ T[:3, :3]
    return np.all((local >= lo - np.asarray(grow_lo_mm, float)) & (local <= hi + np.asarray(grow_hi_mm, float)), axis=1)


def keep_part_single_setup(points_mm: np.ndarray, normals: np.ndarray, *, up, link_mm: float,
                           part_bounds_mm: tuple, T_frame_part: np.ndarray | None = None,
                           placement_tolerance_mm: float = 0.0, box_margin_mm: float = 2.0,
                           plane_clearance_mm: float, size_tolerance: float,
                           min_seen_fraction: float) -> SingleSetupResult:
    """The part's points in a single setup's merged cloud (see the module's description).

    points_mm, normals : (n, 3), mm / unit (NaN normals allowed), in one frame; up : (3,) the
    cell's up direction in that frame; link_mm : the component cell edge, mm (as
    ``keep_specimen_components``); part_bounds_mm : the drawing's box in the specimen frame,
    ((x0, y0, z0), (x1, y1, z1)) mm; T_frame_part : (4, 4) the part's nominal placement in the
    points' frame, or None (no box crop); placement_tolerance_mm, box_margin_mm : how far the box
    is grown; plane_clearance_mm : points within this of the fixture plane go with it;
    size_tolerance : the kept body's two longest extents may exceed the box's by this fraction;
    min_seen_fraction : and fall short of them down to this fraction.

    Raises :class:`PartNotFound` naming the evidence when nothing of the part's size remains.
    """
    points = check_points("points_mm", points_mm)
    lo, hi = (np.asarray(b, dtype=np.float64) for b in part_bounds_mm)
    if lo.shape != (3,) or hi.shape != (3,) or not (hi > lo).all():
        raise ValueError(f"part_bounds_mm must be (min corner, max corner) with max > min, got {part_bounds_mm}")
    expected = np.sort(hi - lo)[::-1]
    up = _unit("up", up)
    candidate = np.ones(len(points), bool)
    plane = find_fixture_plane(points, normals, up=up)
    below = 0
    if plane is not None:
        candidate &= points @ plane.normal - plane.offset_mm > plane_clearance_mm
        below = int(len(points) - candidate.sum())
    outside = 0
    if T_frame_part is not None:
        T = np.asarray(T_frame_part, dtype=np.float64)
        grow_lo = np.full(3, placement_tolerance_mm + box_margin_mm)
        grow_hi = grow_lo.copy()
        # the part rests on the fixture: the face toward it is where the fixture puts it, whatever
        # the tolerance across; grown by the clearance only, so that supports under it go
        up_part = T[:3, :3].T @ up
        k = int(np.argmax(np.abs(up_part)))
        (grow_lo if up_part[k] > 0 else grow_hi)[k] = plane_clearance_mm
        inside = inside_drawing_box(points, T_frame_part=T, part_bounds_mm=(lo, hi), grow_lo_mm=grow_lo,
                                    grow_hi_mm=grow_hi)
        outside = int(np.count_nonzero(candidate & ~inside))
        candidate &= inside
    where = f"plane {'none found' if plane is None else f'{plane.offset_mm:.2f} mm along up'}"
    if not candidate.any():
        raise PartNotFound(f"single setup: no point is left of the part once the fixture is removed ({where}, "
                           f"{below} points on or below it, {outside} outside the part's placed drawing box)")
    rest = np.flatnonzero(candidate)
    parts = keep_specimen_components(points[rest], link_mm=link_mm, min_extent_mm=0.0)
    largest = parts.labels == 0
    body = points[rest[largest]]
    extents = _principal_extents(body) if len(body) >= 3 else np.zeros(3)
    ratio = extents[:2] / expected[:2]
    if not np.all((ratio >= min_seen_fraction) & (ratio <= 1 + size_tolerance)):
        raise PartNotFound(
            f"single setup: the largest body left once the fixture is removed ({where}, {parts.n_components} "
            f"components) is {extents[0]:.1f} x {extents[1]:.1f} mm along its two longest axes, the part's drawing "
            f"{expected[0]:.1f} x {expected[1]:.1f} mm; expected each within {min_seen_fraction:g} to "
            f"{1 + size_tolerance:g} of it: that body is not the part alone (is the fixture plane seen, the "
            f"setup's T_world_specimen_nominal right, the specimen's dimensions right?)")
    keep = np.zeros(len(points), bool)
    keep[rest[largest]] = True
    return SingleSetupResult(keep=keep, plane=plane, below_plane=below, outside_box=outside,
                             n_components=int(parts.n_components), kept_points=int(largest.sum()),
                             extents_mm=extents, expected_mm=expected)


@dataclass(frozen=True)
class Underside:
    """Points closing the unseen underside: ``points_mm`` (k, 3) on a grid ``spacing_mm`` apart over
    the part's outline seen along ``up``, at ``height_mm`` along it (the lowest kept point);
    ``normals`` (k, 3) all ``-up``."""

    points_mm: np.ndarray
    normals: np.ndarray
    height_mm: float
    spacing_mm: float


def fill_underside(points_mm: np.ndarray, *, up, spacing_mm: float) -> Underside:
    """A plane under the part's points (n, 3) mm, perpendicular to ``up`` (3,), at their lowest
    height, over their outline seen from above (the grid cells their projections occupy, holes
    filled), one point per ``spacing_mm`` cell."""
    points = check_points("points_mm", points_mm)
    if len(points) == 0:
        raise ValueError("points_mm is empty")
    if not (np.isfinite(spacing_mm) and spacing_mm > 0):
        raise ValueError(f"spacing_mm must be positive, got {spacing_mm}")
    up = _unit("up", up)
    helper = np.eye(3)[int(np.argmin(np.abs(up)))]
    e1 = np.cross(up, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    uv = np.column_stack([points @ e1, points @ e2])
    height = float((points @ up).min())
    ij = np.floor(uv / spacing_mm).astype(np.int64)
    lo = ij.min(axis=0) - 1
    shape = tuple(ij.max(axis=0) - lo + 2)
    occupied = np.zeros(shape, bool)
    occupied[ij[:, 0] - lo[0], ij[:, 1] - lo[1]] = True
    cells = np.argwhere(binary_fill_holes(occupied)) + lo
    centres = (cells + 0.5) * spacing_mm
    fill = centres[:, :1] * e1 + centres[:, 1:] * e2 + height * up
    return Underside(points_mm=fill, normals=np.repeat(-up[None], len(fill), 0), height_mm=height,
                     spacing_mm=float(spacing_mm))
