"""Rigid transforms as 4x4 numpy arrays (mm), the one home of the project's frame arithmetic.
``T_a_b`` maps points from frame b to frame a: ``apply(T_a_b, points_b)`` gives ``points_a``."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["make_pose", "rotation_deg", "translation", "invert", "apply", "apply_each", "rotate", "frame_from_axes"]


def make_pose(rotation: np.ndarray, t_mm: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rotation
    T[:3, 3] = t_mm
    return T


def rotation_deg(axis: str, angle_deg: float) -> np.ndarray:
    """A pose that rotates about a principal axis ('x', 'y' or 'z') through the origin."""
    return make_pose(Rotation.from_euler(axis, angle_deg, degrees=True).as_matrix(), np.zeros(3))


def translation(t_mm) -> np.ndarray:
    return make_pose(np.eye(3), np.asarray(t_mm, dtype=float))


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of one pose (4, 4) or of a stack (n, 4, 4)."""
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def apply(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply one pose (4, 4) to points (..., 3)."""
    return points @ T[:3, :3].T + T[:3, 3]


def apply_each(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply pose ``T[k]`` (n, 4, 4) to point ``points[k]`` (n, 3)."""
    return np.einsum("nij,nj->ni", T[:, :3, :3], points) + T[:, :3, 3]


def rotate(T: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """Turn directions (..., 3) by one pose's rotation (4, 4); no translation."""
    return vectors @ T[:3, :3].T


def frame_from_axes(x_axis, y_axis, z_axis, origin) -> np.ndarray:
    """Pose whose rotation columns are the given (orthonormal, right-handed) axes."""
    R = np.column_stack([x_axis, y_axis, z_axis]).astype(float)
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-9) or np.linalg.det(R) < 0:
        raise ValueError("axes must be orthonormal and right-handed")
    return make_pose(R, np.asarray(origin, dtype=float))
