"""One setup's scene: the specimen placed in the cell, the fixture, and the stickers on both."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree
from scipy.special import ndtr

from simulator.specimen import SurfaceMesh
from tasks.cells import ReachGrid
from tasks.frames import apply, invert

__all__ = ["StickerSet", "Scene", "NO_STICKER"]

NO_STICKER = -1


@dataclass(frozen=True)
class StickerSet:
    """Stickers as discs: centres (k, 3) and unit normals (k, 3) in one frame, ids (k,), the
    face (simulator.specimen.Face) each sits on (k,)."""

    centres: np.ndarray
    normals: np.ndarray
    ids: np.ndarray
    faces: np.ndarray
    radius_mm: float
    thickness_mm: float
    _tree: cKDTree | None = field(default=None, init=False, repr=False, compare=False)
    _grids: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def _centre_tree(self) -> cKDTree:
        """A k-d tree of the sticker centres, built on first use (the set itself is frozen)."""
        if self._tree is None:
            object.__setattr__(self, "_tree", cKDTree(self.centres))
        return self._tree

    def _nearest_centre(self, points: np.ndarray, bound_mm: float) -> tuple[np.ndarray, np.ndarray]:
        """``cKDTree.query(points, k=1, distance_upper_bound=bound_mm)`` of the centres: (distance,
        index), inf and len(centres) where no centre is within ``bound_mm``. Most points of a
        profile are far from every sticker: only those a ``tasks.cells.ReachGrid`` of the centres
        says may be within the bound are searched (grids kept for the last few bounds asked for);
        the answer is the same."""
        if bound_mm not in self._grids:
            if len(self._grids) >= 8:
                self._grids.clear()
            self._grids[bound_mm] = ReachGrid(self.centres, bound_mm, max_cells=1 << 22)
        dist = np.full(len(points), np.inf)
        idx = np.full(len(points), len(self.centres), dtype=np.intp)
        near = np.flatnonzero(self._grids[bound_mm].may_reach(points))
        if len(near):
            dist[near], idx[near] = self._centre_tree().query(points[near], k=1, distance_upper_bound=bound_mm)
        return dist, idx

    def lookup(self, points: np.ndarray) -> np.ndarray:
        """Sticker id under each point (n, 3) (same frame), NO_STICKER where none."""
        out = np.full(len(points), NO_STICKER, dtype=np.int32)
        if len(self.ids) == 0 or len(points) == 0:
            return out
        dist, idx = self._nearest_centre(points, self.radius_mm + 0.6)
        near = np.isfinite(dist)
        d = points[near] - self.centres[idx[near]]
        h = np.einsum("ij,ij->i", d, self.normals[idx[near]])
        planar = np.linalg.norm(d - h[:, None] * self.normals[idx[near]], axis=1)
        on = (np.abs(h) < 0.5) & (planar <= self.radius_mm)
        hit = np.flatnonzero(near)[on]
        out[hit] = self.ids[idx[hit]]
        return out

    def radial_mm(self, points: np.ndarray, ids: np.ndarray) -> np.ndarray:
        """From the centre of sticker ``ids`` (n,) (ids as ``lookup`` gives them, none NO_STICKER)
        to each point (n, 3), in the sticker's plane (n, 3)."""
        index = np.searchsorted(self.ids, ids)
        if len(ids) and not np.array_equal(self.ids[np.minimum(index, len(self.ids) - 1)], ids):
            raise ValueError("radial_mm: unknown sticker ids")
        d = points - self.centres[index]
        n = self.normals[index]
        return d - np.einsum("ij,ij->i", d, n)[:, None] * n

    def inside_mm(self, points: np.ndarray, ids: np.ndarray) -> np.ndarray:
        """Signed distance (n,) in the sticker's plane from each point (n, 3) to the rim of sticker
        ``ids`` (n,): > 0 inside the rim."""
        return self.radius_mm - np.linalg.norm(self.radial_mm(points, ids), axis=1)

    def coverage(self, points: np.ndarray, rays: np.ndarray, line_dirs: np.ndarray, scan_dirs: np.ndarray,
                 line_box_mm: np.ndarray, scan_sigma_mm: float) -> np.ndarray:
        """Share (n,) of each point's laser footprint that falls on a sticker, 0..1.

        The footprint is what one profile point's intensity integrates: the camera pixel's width
        along the laser line (a box, ``line_box_mm`` (n,) wide across the ray, along
        ``line_dirs``) times the laser line's thickness (a Gaussian of ``scan_sigma_mm`` along
        ``scan_dirs``). Both are projected along the ray (``rays``, unit, (n, 3)) onto the
        sticker's plane and compared with the signed distance to the nearest sticker's rim.
        """
        frac = np.zeros(len(points))
        if len(self.ids) == 0 or len(points) == 0:
            return frac
        reach = float(np.max(line_box_mm, initial=0.0)) * 4 + 4 * scan_sigma_mm + 0.1
        dist, idx = self._nearest_centre(points, self.radius_mm + reach)
        near = np.flatnonzero(np.isfinite(dist))
        if len(near) == 0:
            return frac
        n = self.normals[idx[near]]
        d = points[near] - self.centres[idx[near]]
        h = np.einsum("ij,ij->i", d, n)
        radial = d - h[:, None] * n
        planar = np.linalg.norm(radial, axis=1)
        u = radial / np.maximum(planar, 1e-9)[:, None]
        inside = self.radius_mm - planar  # signed: > 0 on the sticker
        ray = rays[near]
        ray_n = np.einsum("ij,ij->i", ray, n)
        ray_n = np.where(np.abs(ray_n) < 0.1, np.copysign(0.1, ray_n), ray_n)

        def along_u(v: np.ndarray) -> np.ndarray:  # a footprint direction, cast onto the plane, along u
            onto = v - (np.einsum("ij,ij->i", v, n) / ray_n)[:, None] * ray
            return np.abs(np.einsum("ij,ij->i", onto, u))

        half_box = 0.5 * line_box_mm[near] * along_u(line_dirs[near])
        sigma = np.maximum(scan_sigma_mm * along_u(scan_dirs[near]), 1e-6)
        share = np.zeros(len(near))
        offsets = (np.arange(8) + 0.5) / 8 * 2 - 1  # the box, sampled
        for o in offsets:
            share += ndtr((inside + o * half_box) / sigma)
        frac[near] = np.where(np.abs(h) < 0.5, share / len(offsets), 0.0)
        return frac


class Scene:
    """Ray casting against the placed specimen (geometry 0) and the fixture (geometry 1)."""

    SPECIMEN, FIXTURE = 0, 1

    def __init__(self, specimen_mesh: SurfaceMesh, T_world_specimen: np.ndarray, fixture_mesh: SurfaceMesh,
                 specimen_stickers: StickerSet, fixture_stickers: StickerSet) -> None:
        self.T_world_specimen = T_world_specimen
        self.T_specimen_world = invert(T_world_specimen)
        self.specimen_mesh = specimen_mesh
        self.fixture_mesh = fixture_mesh
        self.specimen_stickers = specimen_stickers
        self.fixture_stickers = fixture_stickers
        self._scene = o3d.t.geometry.RaycastingScene()
        for mesh, T in ((specimen_mesh, T_world_specimen), (fixture_mesh, np.eye(4))):
            vertices = o3d.core.Tensor(apply(T, mesh.vertices).astype(np.float32))
            triangles = o3d.core.Tensor(mesh.triangles.astype(np.uint32))
            self._scene.add_triangles(vertices, triangles)

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> dict[str, np.ndarray]:
        """Cast rays (n, 3) + (n, 3) unit; returns t_hit (inf on miss), geometry and triangle ids,
        outward triangle normals (world)."""
        rays = np.concatenate([origins, directions], axis=1).astype(np.float32)
        result = self._scene.cast_rays(o3d.core.Tensor(rays))
        return {
            "t_hit": result["t_hit"].numpy().astype(np.float64),
            "geometry_id": result["geometry_ids"].numpy().astype(np.int64),
            "triangle_id": result["primitive_ids"].numpy().astype(np.int64),
            "normal": result["primitive_normals"].numpy().astype(np.float64),
        }
