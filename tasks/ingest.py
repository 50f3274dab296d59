"""Ingest: a pass's sensor poses (the robot's log or its nominal sweep) and its (X, Z) profiles
to 3-D points (the coarse alignment)."""

from __future__ import annotations

import numpy as np

from schemas.manifest import NominalMotion

__all__ = ["nominal_flange_poses", "sensor_poses", "profile_points"]


def nominal_flange_poses(motion: NominalMotion, timestamp_s: np.ndarray) -> np.ndarray:
    """T_world_flange (profiles, 4, 4) float64 of the commanded sweep: the start pose moved
    straight along ``direction_world`` at ``speed_mm_s`` for each profile's ``timestamp_s``
    (profiles,) s since the pass started."""
    t = np.asarray(timestamp_s, dtype=np.float64)
    if t.ndim != 1 or not np.isfinite(t).all():
        raise ValueError(f"timestamp_s must be a finite (profiles,) array, got shape {t.shape}")
    T = np.repeat(np.asarray(motion.T_world_flange_start, dtype=np.float64)[None], len(t), axis=0)
    T[:, :3, 3] += (t * motion.speed_mm_s)[:, None] * np.asarray(motion.direction_world, dtype=np.float64)[None]
    return T


def sensor_poses(T_flange_sensor: np.ndarray, *, timestamp_s: np.ndarray, T_world_flange: np.ndarray | None,
                 motion: NominalMotion) -> np.ndarray:
    """T_world_sensor (profiles, 4, 4) float64 of every profile: the robot's logged flange pose
    per profile when there is one (``T_world_flange`` (profiles, 4, 4)), else the nominal sweep,
    composed with the hand-eye transform ``T_flange_sensor`` (4, 4)."""
    T_fs = np.asarray(T_flange_sensor, dtype=np.float64)
    if T_fs.shape != (4, 4) or not np.isfinite(T_fs).all():
        raise ValueError(f"T_flange_sensor must be a finite (4, 4) transform, got shape {T_fs.shape}")
    if T_world_flange is None:
        return nominal_flange_poses(motion, timestamp_s) @ T_fs
    T_wf = np.asarray(T_world_flange, dtype=np.float64)
    n = len(np.asarray(timestamp_s))
    if T_wf.shape != (n, 4, 4):
        raise ValueError(f"T_world_flange must have shape ({n}, 4, 4), one pose per profile, got {T_wf.shape}")
    if not np.isfinite(T_wf).all():
        raise ValueError("T_world_flange holds NaN or inf")
    return T_wf @ T_fs


def profile_points(x_mm: np.ndarray, z_mm: np.ndarray, T_world_sensor: np.ndarray) -> np.ndarray:
    """Organized 3-D points of a pass.

    x_mm, z_mm : (profiles, columns) float, mm, sensor frame S (the laser plane is S's x-z
        plane); NaN marks a missing return.
    T_world_sensor : (profiles, 4, 4) float, the sensor pose of each profile.
    Returns (profiles, columns, 3) float64, mm, world frame; NaN where the return is missing.
    """
    x = np.asarray(x_mm, dtype=np.float64)
    z = np.asarray(z_mm, dtype=np.float64)
    T = np.asarray(T_world_sensor, dtype=np.float64)
    if x.shape != z.shape or x.ndim != 2:
        raise ValueError(f"x_mm and z_mm must be equal (profiles, columns) grids, got {x.shape} and {z.shape}")
    if T.shape != (x.shape[0], 4, 4):
        raise ValueError(f"T_world_sensor must have shape ({x.shape[0]}, 4, 4), got {T.shape}")
    if not np.isfinite(T).all():
        raise ValueError("T_world_sensor holds NaN or inf")
    # y = 0 in S: the point is x times S's x axis plus z times its z axis, from the origin
    out = x[..., None] * T[:, None, :3, 0]
    out += z[..., None] * T[:, None, :3, 2]
    out += T[:, None, :3, 3]
    return out
