"""A fillet weld's root line found in a scan's points: the corner of a T-joint where a stem plate
stands on a base plate, the weld in it (``tasks.fillet_section`` measures its sections).

- The plates: the two dominant planes of the points, each found by RANSAC (``_TRIES`` planes
  through three points drawn with a fixed seed, the one with the most points within
  ``tolerance_mm`` kept, then refitted by least squares on those), the second on the points the
  first leaves. Fewer than ``min_plate_fraction`` of the points on the second, or a second within
  ``_MIN_PLATES_ANGLE_DEG`` of parallel to the first: no stem, no fillet.
- Which is the base: the plate whose points lie on both sides of the other's plane (the base runs
  on under a stem welded on both sides); else the plate whose normal is nearer the file's z (a
  scanner looks down on a base plate lying flat, a stem stands up from it).
- ``up``: the base's normal, toward the side where the stem's points are; ``out``: along the base,
  perpendicular to the root line, toward the weld's side of the stem's plane: where the points on
  neither plate within ``_CORNER_MM`` of the root are (the weld's face), else where most of the
  base's points are. A stem welded on both sides: the corner of the stem face found first. Both perpendicular to the line and to each other, as
  ``measure_fillet_line`` takes them.
- The root line: where the two planes cross (``auto``), or the line given; its ends where the
  points within ``reach_mm`` of it reach along it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["FilletRoot", "Plane", "find_fillet_root"]

_TRIES = 400  # RANSAC planes tried per plate
_SAMPLE = 40_000  # RANSAC counts on at most this many points (a fixed draw); the refit uses them all
_MIN_PLATES_ANGLE_DEG = 30.0  # plates closer to parallel than this are one plate, not a corner
_BOTH_SIDES_MM = 3.0  # a base runs on this far past the stem's plane on either side ...
_BOTH_SIDES_FRACTION = 0.2  # ... with at least this fraction of its points on the lesser side
_CORNER_MM = 8.0  # the weld's points: off both plates within this of the root (under a 10 mm stem's thickness)


@dataclass(frozen=True)
class Plane:
    """A plate's plane: a point on it, its unit normal, the points on it (within tolerance)."""

    point: tuple[float, float, float]
    normal: tuple[float, float, float]
    n_points: int


@dataclass(frozen=True)
class FilletRoot:
    """The fillet's root line (the scan's frame, mm) and the plates around it: ``out`` along the
    base away from the stem, ``up`` along the stem away from the base (unit, perpendicular to the
    line and to each other); ``plates_angle_deg`` between the planes fitted; ``found`` "given" or
    "auto"."""

    start_mm: tuple[float, float, float]
    end_mm: tuple[float, float, float]
    out: tuple[float, float, float]
    up: tuple[float, float, float]
    base: Plane
    stem: Plane
    plates_angle_deg: float
    found: str


def _checked(points: np.ndarray) -> np.ndarray:
    points = np.asarray(points, np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 100 or not np.isfinite(points).all():
        raise ValueError(f"points must be a finite (n >= 100, 3) array, mm; got {points.shape}")
    return points


def _refit(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    mean = points.mean(axis=0)
    _, vectors = np.linalg.eigh(np.cov((points - mean).T))
    return mean, vectors[:, 0]


def _dominant_plane(points: np.ndarray, tolerance_mm: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(point, unit normal, mask of ``points`` within ``tolerance_mm``) of the plane most points lie on."""
    sample = points if len(points) <= _SAMPLE else points[rng.choice(len(points), _SAMPLE, replace=False)]
    best, best_count = None, -1
    for _ in range(_TRIES):
        p = sample[rng.choice(len(sample), 3, replace=False)]
        n = np.cross(p[1] - p[0], p[2] - p[0])
        norm = float(np.linalg.norm(n))
        if norm < 1e-9:
            continue
        n /= norm
        count = int(np.count_nonzero(np.abs((sample - p[0]) @ n) <= tolerance_mm))
        if count > best_count:
            best, best_count = (p[0], n), count
    point, normal = best
    on = np.abs((points - point) @ normal) <= tolerance_mm
    for _ in range(3):  # least squares on its points, then its points again
        point, normal = _refit(points[on])
        on = np.abs((points - point) @ normal) <= tolerance_mm
    return point, normal, on


def find_fillet_root(points: np.ndarray, *, line_mm=None, tolerance_mm: float = 0.3,
                     min_plate_fraction: float = 0.05, reach_mm: float = 32.0) -> FilletRoot:
    """The fillet's root line and plates in ``points`` (n, 3) mm (module description).
    ``line_mm``: the root line given (two points, mm), else found where the plates cross.
    ValueError: a scan without two plates meeting at an angle (no stem), a given line that does
    not run along the corner (more than 30 deg off it) or lies outside the scan."""
    points = _checked(points)
    rng = np.random.default_rng(0)
    p1, n1, on1 = _dominant_plane(points, tolerance_mm, rng)
    rest = points[~on1]
    if len(rest) < max(min_plate_fraction * len(points), 100):
        raise ValueError(f"no stem: {np.count_nonzero(on1) / len(points):.0%} of the points lie on one plane (within "
                         f"{tolerance_mm:g} mm), fewer than {min_plate_fraction:.0%} off it; a fillet scan holds a base "
                         "plate and a stem standing on it, the weld in the corner between them")
    p2, n2, on2_rest = _dominant_plane(rest, tolerance_mm, rng)
    angle = math.degrees(math.acos(min(abs(float(n1 @ n2)), 1.0)))
    if on2_rest.sum() < min_plate_fraction * len(points) or angle < _MIN_PLATES_ANGLE_DEG:
        raise ValueError(f"no stem: the points off the largest plane make no second plate at an angle to it "
                         f"({int(on2_rest.sum())} points on the next plane, {angle:.1f} deg to the first; a fillet "
                         f"scan holds a base plate and a stem standing on it at more than {_MIN_PLATES_ANGLE_DEG:g} deg)")
    planes = [(p1, n1, points[on1]), (p2, n2, rest[on2_rest])]

    def both_sides(k: int) -> bool:  # plate k's points lie on both sides of the other plate's plane
        p, n = planes[1 - k][0], planes[1 - k][1]
        d = (planes[k][2] - p) @ n
        lesser = min(np.count_nonzero(d > _BOTH_SIDES_MM), np.count_nonzero(d < -_BOTH_SIDES_MM))
        return lesser >= _BOTH_SIDES_FRACTION * len(d)

    sides = [both_sides(0), both_sides(1)]
    if sides[0] != sides[1]:
        base_k = 0 if sides[0] else 1
    else:
        base_k = 0 if abs(n1[2]) >= abs(n2[2]) else 1
    (pb, nb, on_base), (ps, ns, on_stem) = planes[base_k], planes[1 - base_k]
    # the corner: where the planes cross
    t = np.cross(nb, ns)
    t /= np.linalg.norm(t)
    A = np.stack([nb, ns, t])
    corner = np.linalg.solve(A, np.array([nb @ pb, ns @ ps, t @ points.mean(axis=0)]))
    found = "auto"
    if line_mm is not None:
        q0, q1 = (np.asarray(v, np.float64) for v in line_mm)
        length = float(np.linalg.norm(q1 - q0))
        if q0.shape != (3,) or q1.shape != (3,) or length == 0:
            raise ValueError(f"a weld line is two different points x,y,z; got {list(line_mm[0])} and {list(line_mm[1])}")
        given = (q1 - q0) / length
        off = math.degrees(math.acos(min(abs(float(given @ t)), 1.0)))
        if off > 30.0:
            raise ValueError(f"the weld line {_xyz(q0)}:{_xyz(q1)} runs {off:.0f} deg off the corner where the scan's "
                             f"two plates meet (along {_xyz(np.round(t, 3))}); a fillet's root line runs along it")
        t, corner, found = given, q0, "given"
    up = nb - (nb @ t) * t
    up /= np.linalg.norm(up)
    if np.median((on_stem - corner) @ up) < 0:  # the stem stands on this side of the base
        up = -up
    out = np.cross(t, up)
    if _weld_side(points, on_base, corner, out, up, (pb, nb), (ps, ns), tolerance_mm) < 0:
        out = -out
    rel = points - corner
    s, a, b = rel @ t, rel @ out, rel @ up
    near = (np.abs(a) <= reach_mm) & (np.abs(b) <= reach_mm)
    if found == "auto":
        s0, s1 = float(s[near].min()), float(s[near].max())
    else:
        s0, s1 = 0.0, float(np.linalg.norm(np.asarray(line_mm[1], np.float64) - corner))
    if np.count_nonzero(near & (s >= s0) & (s <= s1)) < 100:  # (the root itself lies under the weld)
        lo, hi = points.min(axis=0), points.max(axis=0)
        raise ValueError(f"the weld line {_xyz(corner + s0 * t)}:{_xyz(corner + s1 * t)} lies outside the scan (fewer "
                         f"than 100 points within {reach_mm:g} mm of it; the scan spans x {lo[0]:.2f}..{hi[0]:.2f}, "
                         f"y {lo[1]:.2f}..{hi[1]:.2f}, z {lo[2]:.2f}..{hi[2]:.2f} mm)")
    plates = math.degrees(math.acos(float(np.clip(abs(nb @ ns), -1, 1))))
    return FilletRoot(start_mm=tuple(map(float, corner + s0 * t)), end_mm=tuple(map(float, corner + s1 * t)),
                      out=tuple(map(float, out)), up=tuple(map(float, up)),
                      base=Plane(tuple(map(float, pb)), tuple(map(float, nb)), len(on_base)),
                      stem=Plane(tuple(map(float, ps)), tuple(map(float, ns)), len(on_stem)),
                      plates_angle_deg=plates, found=found)


def _weld_side(points, on_base, corner, out, up, base, stem, tolerance_mm: float) -> float:
    """+1 when the weld lies on the ``out`` side of the stem's plane, -1 when on the other: the side
    of the points in the corner (within ``_CORNER_MM`` of the root, above the base) on neither
    plate (the weld's face; the stem's other face, a stem's thickness away, is left out); with
    none there, the side where most of the base's points are."""
    rel = points - corner
    a, b = rel @ out, rel @ up
    off = ((np.abs((points - base[0]) @ base[1]) > 2 * tolerance_mm)
           & (np.abs((points - stem[0]) @ stem[1]) > 2 * tolerance_mm))
    weld = off & (np.abs(a) < _CORNER_MM) & (b > 0) & (b < _CORNER_MM)
    if np.count_nonzero(weld) >= 20:
        return float(np.sign(np.median(a[weld])) or 1.0)
    return 1.0 if np.count_nonzero((on_base - corner) @ out > 0) >= 0.5 * len(on_base) else -1.0


def _xyz(p: np.ndarray) -> str:
    return ",".join(f"{v:g}" for v in p)
