"""A triangulating laser line scanner.

The laser fans out in the sensor's x-z plane from the sensor origin; column i is the ray with
x/z = (i - (n-1)/2) * x_spacing / reference_distance. The camera sits at ``camera_offset_mm`` in
the sensor frame and must see the laser spot (occlusion -> shadow). Per point the sensor reports
X and Z in the sensor frame and a 10-bit backscatter intensity.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schemas.simulation import ScannerConfig
from schemas.truth import Material, PointLabel
from simulator.scene import NO_STICKER, Scene
from tasks.frames import apply, invert

__all__ = ["Profiles", "LineScanner", "fan_directions"]

_REFLECTANCE = {Material.STEEL: 0.45, Material.GROUND: 0.12, Material.STICKER: 0.95,
                Material.FIXTURE: 0.30, Material.FIXTURE_STICKER: 0.95}
_NOISE_FACTOR = {Material.STEEL: 1.0, Material.GROUND: 2.5, Material.STICKER: 1.3,
                 Material.FIXTURE: 1.2, Material.FIXTURE_STICKER: 1.3}
_SHADOW_TOLERANCE_MM = 0.02
_NO_FACE = 255


def fan_directions(points_per_profile: int, x_spacing_mm: float, reference_distance_mm: float) -> np.ndarray:
    """Unit laser ray directions (n, 3) in the sensor frame."""
    tan = (np.arange(points_per_profile) - (points_per_profile - 1) / 2) * x_spacing_mm / reference_distance_mm
    d = np.stack([tan, np.zeros_like(tan), np.ones_like(tan)], axis=1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@dataclass(frozen=True)
class Profiles:
    """A block of simulated profiles; every array is (m profiles, n columns)."""

    x_mm: np.ndarray  # float32, NaN where nothing was reported
    z_mm: np.ndarray
    intensity: np.ndarray  # uint16, 0 where nothing was reported
    label: np.ndarray  # uint8, PointLabel
    material: np.ndarray  # uint8, Material
    sticker_id: np.ndarray  # int16, -1 for none
    face_id: np.ndarray  # uint8, specimen Face of the true surface hit, 255 for none
    point_specimen: np.ndarray | None  # (m, n, 3) float32, true surface hit, specimen frame


class LineScanner:
    def __init__(self, cfg: ScannerConfig) -> None:
        self.cfg = cfg
        self.fan = fan_directions(cfg.points_per_profile, cfg.x_spacing_mm, cfg.reference_distance_mm)
        self.camera_offset = np.asarray(cfg.camera_offset_mm, dtype=float)
        self._cos_grazing = np.cos(np.radians(cfg.grazing_limit_deg))

    def render(self, scene: Scene, T_world_sensor: np.ndarray, rng: np.random.Generator | None, *,
               keep_specimen_points: bool = False) -> Profiles:
        """Simulate the profiles taken at the true sensor poses (m, 4, 4). Without ``rng`` the
        sensor is ideal: no noise, dropouts or outliers (used for planning)."""
        cfg = self.cfg
        m, n = len(T_world_sensor), len(self.fan)
        R, o = T_world_sensor[:, :3, :3], T_world_sensor[:, :3, 3]
        d = np.einsum("mij,nj->mni", R, self.fan).reshape(-1, 3)
        origin = np.repeat(o, n, axis=0)
        hit = scene.cast(origin, d)
        t = hit["t_hit"]
        found = np.isfinite(t)
        t_safe = np.where(found, t, 0.0)
        fan_z = np.tile(self.fan[:, 2], m)
        fan_x = np.tile(self.fan[:, 0], m)
        near, far = cfg.z_range_mm
        in_range = found & (t_safe * fan_z >= near) & (t_safe * fan_z <= far)

        geom, tri = hit["geometry_id"], hit["triangle_id"]
        on_specimen = in_range & (geom == Scene.SPECIMEN)
        on_fixture = in_range & (geom == Scene.FIXTURE)
        normal = hit["normal"]
        cos_l = -np.einsum("ij,ij->i", d, normal)
        point = origin + t_safe[:, None] * d

        face = np.full(m * n, _NO_FACE, np.uint8)
        face[on_specimen] = scene.specimen_mesh.face_id[tri[on_specimen]]
        material = np.zeros(m * n, np.uint8)
        material[on_fixture] = Material.FIXTURE
        material[on_specimen] = np.where(scene.specimen_mesh.reflective[tri[on_specimen]],
                                         Material.GROUND, Material.STEEL)
        # A sticker is a disc on top of the surface: the ray is on it where it crosses the disc's
        # top plane (one thickness above the surface) within its radius.
        thickness = scene.specimen_stickers.thickness_mm
        t_top = t_safe - thickness / np.maximum(cos_l, 0.2)
        top = origin + t_top[:, None] * d
        sticker = np.full(m * n, NO_STICKER, np.int32)
        sticker[on_specimen] = scene.specimen_stickers.lookup(apply(scene.T_specimen_world, top[on_specimen]))
        sticker[on_fixture] = scene.fixture_stickers.lookup(top[on_fixture])
        has_sticker = sticker != NO_STICKER
        base = material.copy()  # what lies under a sticker
        material[has_sticker & on_specimen] = Material.STICKER
        material[has_sticker & on_fixture] = Material.FIXTURE_STICKER
        t_surf = np.where(has_sticker, t_top, t_safe)
        # The paper's edge: a ray that crosses the top plane outside a sticker's rim but would
        # meet the surface inside it runs into the sticker's wall (the side facing the sensor at
        # an oblique view, one thickness high) and is reported there, on paper. Seen from the
        # laser the sticker is wider on that side by thickness * tan(incidence).
        metal = origin + t_safe[:, None] * d
        wall = np.zeros(m * n, bool)
        cos_wall = np.zeros(m * n)
        for where, stickers, T in ((on_specimen, scene.specimen_stickers, scene.T_specimen_world),
                                   (on_fixture, scene.fixture_stickers, np.eye(4))):
            rays = np.flatnonzero(where & ~has_sticker)
            metal_s = apply(T, metal[rays])
            under = stickers.lookup(metal_s)
            hit = under != NO_STICKER
            rays, ids, metal_s = rays[hit], under[hit], metal_s[hit]
            a = stickers.inside_mm(apply(T, top[rays]), ids)  # < 0: the top plane is crossed outside
            b = stickers.inside_mm(metal_s, ids)  # >= 0: the surface is met inside
            t_wall = t_top[rays] + np.clip(-a / np.maximum(b - a, 1e-12), 0.0, 1.0) * (t_safe[rays] - t_top[rays])
            wall[rays] = True
            sticker[rays] = ids
            t_surf[rays] = t_wall
            radial = stickers.radial_mm(apply(T, origin[rays] + t_wall[:, None] * d[rays]), ids)
            outward = (radial / np.maximum(np.linalg.norm(radial, axis=1), 1e-9)[:, None]) @ invert(T)[:3, :3].T
            cos_wall[rays] = -np.einsum("ij,ij->i", d[rays], outward)
        has_sticker |= wall
        material[wall & on_specimen] = Material.STICKER
        material[wall & on_fixture] = Material.FIXTURE_STICKER
        point = origin + t_surf[:, None] * d

        camera = o + self.camera_offset @ R.transpose(0, 2, 1)  # (m, 3)
        camera = np.repeat(camera, n, axis=0)
        to_cam = camera - point
        dist_cam = np.linalg.norm(to_cam, axis=1)
        to_cam /= np.maximum(dist_cam, 1e-9)[:, None]
        cos_c = np.einsum("ij,ij->i", to_cam, normal)
        grazing = in_range & ((cos_l < self._cos_grazing) | (cos_c < self._cos_grazing))
        check = in_range & ~grazing
        shadow = np.zeros(m * n, bool)
        if check.any():
            back = scene.cast(camera[check], -to_cam[check])
            shadow[check] = back["t_hit"] < dist_cam[check] - _SHADOW_TOLERANCE_MM

        label = np.full(m * n, PointLabel.NO_SURFACE, np.uint8)
        label[in_range] = PointLabel.VALID
        label[grazing] = PointLabel.GRAZING
        label[shadow] = PointLabel.SHADOW
        seen = label == PointLabel.VALID

        t_meas = t_surf.copy()
        intensity_noise = np.zeros(m * n)
        if rng is not None:
            gauss, u_drop, u_out, u_sign, u_mag, i_noise = (
                rng.standard_normal(m * n), rng.random(m * n), rng.random(m * n),
                rng.random(m * n), rng.random(m * n), rng.standard_normal(m * n))
            factor = np.ones(m * n)
            for mat, f in _NOISE_FACTOR.items():
                factor[material == mat] = f
            sigma = cfg.range_noise_mm * factor * (1 + 0.5 * (1 / np.maximum(cos_c, 0.2) - 1))
            t_meas = t_meas + sigma * gauss
            reflective = material == Material.GROUND
            drop_rate = np.where(reflective, cfg.reflective_dropout_rate, cfg.dropout_rate)
            out_rate = np.where(reflective, cfg.reflective_outlier_rate, cfg.outlier_rate)
            dropout = seen & (u_drop < drop_rate)
            outlier = seen & ~dropout & (u_out < out_rate)
            lo, hi = cfg.outlier_offset_mm
            t_meas = np.where(outlier, t_meas + np.where(u_sign < 0.5, -1, 1) * (lo + (hi - lo) * u_mag), t_meas)
            label[dropout] = PointLabel.DROPOUT
            label[outlier] = PointLabel.OUTLIER
            intensity_noise = cfg.intensity_noise * i_noise
        z_meas = t_meas * fan_z
        reported = (label == PointLabel.VALID) | (label == PointLabel.OUTLIER)
        lost = reported & ((z_meas < near) | (z_meas > far))
        label[lost] = PointLabel.NO_SURFACE
        reported &= ~lost
        z_q = np.round(z_meas / cfg.z_resolution_mm) * cfg.z_resolution_mm
        x_q = z_q * fan_x / fan_z

        # Reflectance over each point's footprint: a rim point reads partly sticker, partly metal.
        line_dirs = np.repeat(R[:, :, 0], n, axis=0)
        scan_dirs = np.repeat(R[:, :, 1], n, axis=0)
        box = cfg.x_spacing_mm * np.maximum(t_surf * fan_z, 1.0) / cfg.reference_distance_mm
        sigma = cfg.line_width_mm / 4
        # The footprint's share on paper, the top and the wall both: where the ray crosses the top
        # plane (the far rim) or meets the surface (the near rim, behind the wall), whichever is
        # further inside.
        share = np.zeros(m * n)
        S = scene.T_specimen_world[:3, :3]
        for at in (top, metal):
            share[on_specimen] = np.maximum(share[on_specimen], scene.specimen_stickers.coverage(
                apply(scene.T_specimen_world, at[on_specimen]), d[on_specimen] @ S.T, line_dirs[on_specimen] @ S.T,
                scan_dirs[on_specimen] @ S.T, box[on_specimen], sigma))
            share[on_fixture] = np.maximum(share[on_fixture], scene.fixture_stickers.coverage(
                at[on_fixture], d[on_fixture], line_dirs[on_fixture], scan_dirs[on_fixture], box[on_fixture], sigma))
        reflectance = np.zeros(m * n)
        for mat, rho in _REFLECTANCE.items():
            reflectance[base == mat] = rho
        reflectance += share * (_REFLECTANCE[Material.STICKER] - reflectance)
        distance_gain = (cfg.reference_distance_mm / np.maximum(t_surf * fan_z, 1.0)) ** 2
        level = 900 * reflectance * np.clip(np.where(wall, cos_wall, cos_l), 0, 1) ** 0.8 * distance_gain
        mirror = d + 2 * cos_l[:, None] * normal
        spec_angle = np.arccos(np.clip(np.einsum("ij,ij->i", mirror, to_cam), -1, 1))
        level += np.where(base == Material.GROUND,
                          (1 - share) * 1500 * np.exp(-0.5 * (spec_angle / np.radians(6)) ** 2), 0)
        intensity = np.clip(np.round(level + intensity_noise), 1, 1023).astype(np.uint16)

        shape = (m, n)
        return Profiles(
            x_mm=np.where(reported, x_q, np.nan).astype(np.float32).reshape(shape),
            z_mm=np.where(reported, z_q, np.nan).astype(np.float32).reshape(shape),
            intensity=np.where(reported, intensity, 0).astype(np.uint16).reshape(shape),
            label=label.reshape(shape),
            material=material.reshape(shape),
            sticker_id=sticker.astype(np.int16).reshape(shape),
            face_id=face.reshape(shape),
            point_specimen=(np.where(found[:, None], apply(scene.T_specimen_world, point), np.nan)
                            .astype(np.float32).reshape(m, n, 3) if keep_specimen_points else None),
        )


