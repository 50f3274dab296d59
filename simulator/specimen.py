"""The virtual specimen: a welded S355 dog-bone plate as a closed triangle mesh.

Specimen frame: origin at the plate's centre, x along the length, y across, z through the
thickness (top face at +t/2). The top and bottom faces are height fields on a grid that
conforms to the dog-bone outline (y = v * half_width(x), v in [-1, 1]); the water-jet-cut walls
join the two faces' boundary rings, so the mesh is closed by construction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d

from schemas.simulation import TrueMeshConfig, SpecimenConfig, WeldConfig
from simulator.weld import WeldCap, draw_weld_cap
from tasks.pass_coverage import dog_bone_half_width

__all__ = ["Face", "SurfaceMesh", "Specimen", "build_specimen"]


class Face:
    TOP, BOTTOM, SIDE_NEG, SIDE_POS, END_POS, END_NEG, FIXTURE = range(7)
    STEM_NEG, STEM_POS, STEM_TOP, WELD = range(7, 11)  # a T-joint's stem (faces x < 0, x > 0, its end), its welds
    STEM_BOTTOM = 11  # a cruciform's lower stem's end (its faces x < 0, x > 0 are STEM_NEG, STEM_POS below the base)
    NAMES = ("top", "bottom", "side_neg", "side_pos", "end_pos", "end_neg", "fixture",
             "stem_neg", "stem_pos", "stem_top", "weld", "stem_bottom")


@dataclass(frozen=True)
class SurfaceMesh:
    vertices: np.ndarray  # (n, 3) float64, mm
    triangles: np.ndarray  # (m, 3) int32, outward winding
    face_id: np.ndarray  # (m,) uint8, Face.*
    reflective: np.ndarray  # (m,) bool, burr-ground metal

    def signed_volume_mm3(self) -> float:
        v = self.vertices[self.triangles]
        return float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6)


@dataclass(frozen=True)
class Specimen:
    config: SpecimenConfig
    weld_top: WeldCap
    weld_bottom: WeldCap
    axial_misalignment_mm: float
    angular_misalignment_deg: float
    mesh: SurfaceMesh

    def half_width(self, x: np.ndarray) -> np.ndarray:
        return _half_width(self.config, x)

    def z_shift(self, x: np.ndarray) -> np.ndarray:
        return _z_shift(x, self.weld_top.centre_x_mm, self.axial_misalignment_mm, self.angular_misalignment_deg)

    def top_z(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return self.config.thickness_mm / 2 + self.z_shift(x) + self.weld_top.height_mm(x, y)[0]

    def bottom_z(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return -self.config.thickness_mm / 2 + self.z_shift(x) - self.weld_bottom.height_mm(x, y)[0]

    def weld_zone_half_mm(self) -> float:
        return max(self.weld_top.max_half_extent_mm(), self.weld_bottom.max_half_extent_mm())


def _half_width(cfg: SpecimenConfig, x: np.ndarray) -> np.ndarray:
    return dog_bone_half_width(x, gauge_length_mm=cfg.gauge_length_mm, gauge_width_mm=cfg.gauge_width_mm,
                               grip_width_mm=cfg.grip_width_mm, transition_radius_mm=cfg.transition_radius_mm)


def _z_shift(x: np.ndarray, centre: float, axial_mm: float, angular_deg: float) -> np.ndarray:
    """Misalignment: the plate at x > centre sits ``axial_mm`` higher and tilted ``angular_deg``."""
    x = np.asarray(x, dtype=float)
    blend = np.clip((x - centre + 3.0) / 6.0, 0, 1)
    blend = blend * blend * (3 - 2 * blend)
    return blend * (axial_mm + np.maximum(x - centre, 0) * np.tan(np.radians(angular_deg)))


def _x_nodes(length: float, weld_half: float, toe_band: tuple[float, float], mesh: TrueMeshConfig) -> np.ndarray:
    """Node positions along x: fine at the toes, finer in the weld zone, coarse on the plates."""

    def spacing(x: float) -> float:
        ax = abs(x)
        if toe_band[0] <= ax <= toe_band[1]:
            return mesh.toe_dx_mm
        if ax <= weld_half:
            return mesh.weld_dx_mm
        # grow smoothly away from the weld zone
        return min(mesh.plate_dx_mm, mesh.weld_dx_mm + 0.2 * (ax - weld_half))

    xs = [-length / 2]
    while xs[-1] < length / 2:
        xs.append(xs[-1] + spacing(xs[-1]))
    xs = np.array(xs)
    xs[-1] = length / 2
    if xs[-1] - xs[-2] < 1e-3:
        xs = np.delete(xs, -2)
    return xs


def _grid_triangles(rows: int, cols: int, offset: int, flip: bool) -> np.ndarray:
    i, j = np.meshgrid(np.arange(rows - 1), np.arange(cols - 1), indexing="ij")
    a = (i * cols + j).ravel() + offset
    b = ((i + 1) * cols + j).ravel() + offset
    c = ((i + 1) * cols + j + 1).ravel() + offset
    d = (i * cols + j + 1).ravel() + offset
    tris = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return tris[:, ::-1] if flip else tris


def _wall_roughness(rng: np.random.Generator, ring_s: np.ndarray, z_frac: np.ndarray, cfg: SpecimenConfig) -> np.ndarray:
    """Water-jet striations: correlated along the cut, lagging with depth; plus kerf taper."""
    step = 0.25
    n = int(np.ceil(ring_s[-1] / step)) + 8
    noise = gaussian_filter1d(rng.standard_normal(n), sigma=2.0)
    noise *= cfg.cut_roughness_mm / max(noise.std(), 1e-12)
    lag = 1.5 * z_frac[None, :] ** 2
    s = ring_s[:, None] + lag
    rough = np.interp(s, np.arange(n) * step, noise) * (0.5 + z_frac[None, :])
    return rough + cfg.cut_taper_mm * (z_frac[None, :] - 0.5)


def build_specimen(cfg: SpecimenConfig, weld_cfg: WeldConfig, mesh_cfg: TrueMeshConfig,
                   rng: np.random.Generator, *, weld_centre_x_mm: float = 0.0) -> Specimen:
    """Draw the welds and misalignment, then mesh the closed specimen surface."""
    y_extent = cfg.grip_width_mm / 2
    weld_top = draw_weld_cap(weld_cfg, rng, centre_x_mm=weld_centre_x_mm, y_extent_mm=y_extent)
    weld_bottom = draw_weld_cap(weld_cfg, rng, centre_x_mm=weld_centre_x_mm, y_extent_mm=y_extent)
    axial = float(rng.uniform(*weld_cfg.axial_misalignment_mm))
    angular = float(rng.uniform(*weld_cfg.angular_misalignment_deg))

    weld_half = max(weld_top.max_half_extent_mm(), weld_bottom.max_half_extent_mm()) + 2.0
    toe_band = (weld_cfg.cap_width_mm[0] / 2 - 1.5 - weld_cfg.bead_wander_mm, weld_half)
    xs = _x_nodes(cfg.length_mm, weld_half + 3.0, toe_band, mesh_cfg) + 0.0
    vs = np.linspace(-1.0, 1.0, mesh_cfg.across_nodes)
    X = np.repeat(xs[:, None], vs.size, axis=1)
    Y = vs[None, :] * _half_width(cfg, xs)[:, None]
    shift = _z_shift(X, weld_centre_x_mm, axial, angular)
    cap_top, refl_top = weld_top.height_mm(X, Y)
    cap_bot, refl_bot = weld_bottom.height_mm(X, Y)
    Z_top = cfg.thickness_mm / 2 + shift + cap_top
    Z_bot = -cfg.thickness_mm / 2 + shift - cap_bot

    nx, nv = X.shape
    n_grid = nx * nv
    top = np.stack([X, Y, Z_top], -1).reshape(-1, 3)
    bot = np.stack([X, Y, Z_bot], -1).reshape(-1, 3)
    tri_top = _grid_triangles(nx, nv, 0, flip=False)
    tri_bot = _grid_triangles(nx, nv, n_grid, flip=True)

    # Boundary ring, counter-clockwise seen from +z: y<0 side, +x end, y>0 side, -x end.
    ring_ij = ([(i, 0) for i in range(nx - 1)] + [(nx - 1, j) for j in range(nv - 1)]
               + [(i, nv - 1) for i in range(nx - 1, 0, -1)] + [(0, j) for j in range(nv - 1, 0, -1)])
    ring_ij = np.array(ring_ij)
    ring_face = np.concatenate([
        np.full(nx - 1, Face.SIDE_NEG), np.full(nv - 1, Face.END_POS),
        np.full(nx - 1, Face.SIDE_POS), np.full(nv - 1, Face.END_NEG)]).astype(np.uint8)
    ring_idx = ring_ij[:, 0] * nv + ring_ij[:, 1]
    ring_top, ring_bot = top[ring_idx], bot[ring_idx]
    n_ring = ring_idx.size
    seg = np.roll(ring_top[:, :2], -1, axis=0) - ring_top[:, :2]
    ring_s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(seg, axis=1))[:-1]])
    tangent = np.roll(ring_top[:, :2], -1, axis=0) - np.roll(ring_top[:, :2], 1, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    outward = np.stack([tangent[:, 1], -tangent[:, 0]], 1)

    rows = mesh_cfg.wall_rows
    z_frac = np.linspace(0, 1, rows)
    rough = _wall_roughness(rng, np.append(ring_s, ring_s[-1] + np.linalg.norm(seg[-1])), z_frac, cfg)[:-1]
    inner = z_frac[1:-1]
    wall = ring_top[:, None, :] * (1 - inner[None, :, None]) + ring_bot[:, None, :] * inner[None, :, None]
    wall[..., :2] += outward[:, None, :] * rough[:, 1:-1, None]
    wall_offset = 2 * n_grid
    wall_vertices = wall.reshape(-1, 3)

    # index[a, k]: vertex of ring position a at wall row k (0 = top ring, rows-1 = bottom ring)
    index = np.empty((n_ring, rows), dtype=np.int64)
    index[:, 0] = ring_idx
    index[:, -1] = ring_idx + n_grid
    index[:, 1:-1] = wall_offset + np.arange(n_ring * (rows - 2)).reshape(n_ring, rows - 2)
    a = np.arange(n_ring)
    b = np.roll(a, -1)
    quads = []
    for k in range(rows - 1):
        p, q, r, s = index[a, k], index[b, k], index[b, k + 1], index[a, k + 1]
        quads.append(np.stack([p, r, q], 1))
        quads.append(np.stack([p, s, r], 1))
    tri_wall = np.concatenate(quads)
    wall_face = np.tile(ring_face, 2 * (rows - 1))

    vertices = np.concatenate([top, bot, wall_vertices])
    triangles = np.concatenate([tri_top, tri_bot, tri_wall]).astype(np.int32)
    face_id = np.concatenate([
        np.full(len(tri_top), Face.TOP), np.full(len(tri_bot), Face.BOTTOM), wall_face]).astype(np.uint8)
    refl_vertex = np.concatenate([refl_top.ravel(), refl_bot.ravel(), np.zeros(len(wall_vertices), bool)])
    reflective = refl_vertex[triangles].all(axis=1)
    mesh = SurfaceMesh(vertices=vertices, triangles=triangles, face_id=face_id, reflective=reflective)
    return Specimen(config=cfg, weld_top=weld_top, weld_bottom=weld_bottom, axial_misalignment_mm=axial,
                    angular_misalignment_deg=angular, mesh=mesh)
