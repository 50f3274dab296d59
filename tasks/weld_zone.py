"""The weld zone, the one definition of it: the space within a radius of the weld lines (polylines
in the frame of the points asked about, mm), the union of the capsules round their segments. The
merge keeps it at full resolution, the FE model names its surface (``WELD_ZONE_SURFACE``) and the
QA page draws it; each asks this module, so the three are the same zone by construction."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["PolylineZone", "WeldZone", "weld_zone", "polyline_projection"]


def polyline_projection(points_mm: np.ndarray, vertices_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each of ``points_mm`` (n, 3) against the polyline ``vertices_mm`` (k >= 2, 3): (distance
    (n,), station (n,)), its distance to the polyline and the arc length from the first vertex to
    its closest point on it, mm (the first segment wins a tie)."""
    p = np.asarray(points_mm, np.float64).reshape(-1, 3)
    vertices = np.asarray(vertices_mm, np.float64)
    best = np.full(len(p), np.inf)
    station = np.zeros(len(p))
    start = 0.0
    for a, b in zip(vertices[:-1], vertices[1:]):
        d = b - a
        dd = float(d @ d)
        t = np.clip((p - a) @ d / max(dd, 1e-300), 0.0, 1.0)
        r = p - a - t[:, None] * d
        squared = np.einsum("ij,ij->i", r, r)
        closer = squared < best
        length = np.sqrt(dd)
        station[closer] = start + t[closer] * length
        best = np.minimum(best, squared)
        start += length
    return np.sqrt(best), station


@dataclass(frozen=True)
class PolylineZone:
    """The space within ``radius_mm`` of a polyline: the union of the capsules round its segments,
    e.g. the zone kept fine around a weld line. ``points_mm``: its k >= 2 vertices in the cloud's
    frame, mm."""

    points_mm: tuple[tuple[float, float, float], ...]
    radius_mm: float

    def distance_mm(self, points_mm: np.ndarray) -> np.ndarray:
        """(n,) float64: the distance of each of ``points_mm`` (n, 3) to the polyline, mm."""
        return polyline_projection(points_mm, np.asarray(self.points_mm, np.float64))[0]

    def contains(self, points_mm: np.ndarray) -> np.ndarray:
        """(n,) bool: the point lies within ``radius_mm`` of the polyline. Points outside the
        zone's bounding box (most of a slab away from the weld) cost one comparison each."""
        p = np.asarray(points_mm, np.float64).reshape(-1, 3)
        vertices = np.asarray(self.points_mm, np.float64)
        near = np.all((p >= vertices.min(axis=0) - self.radius_mm) & (p <= vertices.max(axis=0) + self.radius_mm),
                      axis=1)
        inside = np.zeros(len(p), bool)
        inside[near] = self.distance_mm(p[near]) <= self.radius_mm
        return inside


@dataclass(frozen=True)
class WeldZone:
    """The union of ``zones``: one capsule chain per weld line."""

    zones: tuple[PolylineZone, ...]

    def contains(self, points_mm: np.ndarray) -> np.ndarray:
        """(n,) bool: the point lies within the zone of at least one line."""
        p = np.asarray(points_mm, np.float64).reshape(-1, 3)
        inside = np.zeros(len(p), bool)
        for zone in self.zones:
            inside |= zone.contains(p)
        return inside

    def distance_mm(self, points_mm: np.ndarray) -> np.ndarray:
        """(n,) float64: each point's distance to the nearest line, mm (inf: no line)."""
        p = np.asarray(points_mm, np.float64).reshape(-1, 3)
        best = np.full(len(p), np.inf)
        for zone in self.zones:
            best = np.minimum(best, zone.distance_mm(p))
        return best

    def faces_in(self, vertices_mm: np.ndarray, triangles: np.ndarray) -> np.ndarray:
        """(t,) bool: the triangles (t, 3) of ``vertices_mm`` (v, 3) whose centroid lies in the
        zone: the faces the FE model names and the QA page colours."""
        return self.contains(np.asarray(vertices_mm, np.float64)[np.asarray(triangles)].mean(axis=1))

    def __bool__(self) -> bool:
        return bool(self.zones)


def weld_zone(lines_mm: list[np.ndarray], radius_mm: float | list[float]) -> WeldZone:
    """The zone within ``radius_mm`` (one for all lines, or one per line) of ``lines_mm``, each a
    (k >= 2, 3) polyline, mm. No line or a radius of 0: an empty zone."""
    radii = list(radius_mm) if isinstance(radius_mm, (list, tuple)) else [float(radius_mm)] * len(lines_mm)
    if len(radii) != len(lines_mm):
        raise ValueError(f"weld_zone: {len(lines_mm)} lines but {len(radii)} radii")
    zones = []
    for line, r in zip(lines_mm, radii):
        line = np.asarray(line, np.float64)
        if line.ndim != 2 or line.shape[1] != 3 or len(line) < 2:
            raise ValueError(f"weld_zone: a line must be (k >= 2, 3) points, mm; got shape {line.shape}")
        if r > 0:
            zones.append(PolylineZone(tuple(tuple(float(v) for v in p) for p in line), float(r)))
    return WeldZone(tuple(zones))
