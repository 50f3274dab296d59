"""The fixture: a base plate (top face at world z = 0) and two support blocks under the grips."""

from __future__ import annotations

import numpy as np

from schemas.simulation import FixtureConfig
from simulator.specimen import Face, SurfaceMesh

__all__ = ["build_fixture", "box_mesh", "block_top_z"]

_BOX_TRIANGLES = np.array([
    [0, 2, 1], [0, 3, 2],  # bottom (-z)
    [4, 5, 6], [4, 6, 7],  # top (+z)
    [0, 1, 5], [0, 5, 4],  # -y
    [1, 2, 6], [1, 6, 5],  # +x
    [2, 3, 7], [2, 7, 6],  # +y
    [3, 0, 4], [3, 4, 7],  # -x
], dtype=np.int32)


def box_mesh(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    corners = np.array([[lo[0], lo[1], lo[2]], [hi[0], lo[1], lo[2]], [hi[0], hi[1], lo[2]], [lo[0], hi[1], lo[2]],
                        [lo[0], lo[1], hi[2]], [hi[0], lo[1], hi[2]], [hi[0], hi[1], hi[2]], [lo[0], hi[1], hi[2]]])
    return corners, _BOX_TRIANGLES.copy()


def block_top_z(cfg: FixtureConfig) -> float:
    return cfg.block_size_mm[2]


def build_fixture(cfg: FixtureConfig) -> SurfaceMesh:
    px, py, pz = cfg.plate_size_mm
    bx, by, bz = cfg.block_size_mm
    boxes = [box_mesh((-px / 2, -py / 2, -pz), (px / 2, py / 2, 0.0))]
    boxes += [box_mesh((cx - bx / 2, -by / 2, 0.0), (cx + bx / 2, by / 2, bz)) for cx in cfg.block_centres_x_mm]
    vertices, triangles, offset = [], [], 0
    for v, t in boxes:
        vertices.append(v)
        triangles.append(t + offset)
        offset += len(v)
    triangles = np.concatenate(triangles)
    return SurfaceMesh(vertices=np.concatenate(vertices), triangles=triangles,
                       face_id=np.full(len(triangles), Face.FIXTURE, np.uint8),
                       reflective=np.zeros(len(triangles), bool))
