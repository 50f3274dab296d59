"""Ingest: a pass's (X, Z) profiles and sensor poses to 3-D points (coarse alignment)."""

from __future__ import annotations

import numpy as np

__all__ = ["profile_points"]


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
    local = np.stack([x, np.zeros_like(x), z], axis=-1)
    return np.einsum("nij,nkj->nki", T[:, :3, :3], local) + T[:, None, :3, 3]
