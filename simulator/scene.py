"""One setup's scene: the specimen placed in the cell, the fixture, and the stickers on both."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from simulator.specimen import SurfaceMesh
from simulator.transforms import apply, invert

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

    def lookup(self, points: np.ndarray) -> np.ndarray:
        """Sticker id under each point (n, 3) (same frame), NO_STICKER where none."""
        out = np.full(len(points), NO_STICKER, dtype=np.int32)
        if len(self.ids) == 0 or len(points) == 0:
            return out
        tree = self._tree
        if tree is None:
            tree = cKDTree(self.centres)
            object.__setattr__(self, "_tree", tree)
        dist, idx = tree.query(points, k=1, distance_upper_bound=self.radius_mm + 0.6)
        near = np.isfinite(dist)
        d = points[near] - self.centres[idx[near]]
        h = np.einsum("ij,ij->i", d, self.normals[idx[near]])
        planar = np.linalg.norm(d - h[:, None] * self.normals[idx[near]], axis=1)
        on = (np.abs(h) < 0.5) & (planar <= self.radius_mm)
        hit = np.flatnonzero(near)[on]
        out[hit] = self.ids[idx[hit]]
        return out


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
