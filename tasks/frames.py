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


def turn_about_axis(point_mm, direction, angle_deg: float) -> np.ndarray:
    """(4, 4): a turn of ``angle_deg`` (right-handed) about the line through ``point_mm`` along
    ``direction``."""
    from scipy.spatial.transform import Rotation

    d = np.asarray(direction, float)
    R = Rotation.from_rotvec(np.radians(angle_deg) * d / np.linalg.norm(d)).as_matrix()
    c = np.asarray(point_mm, float)
    return make_pose(R, c - R @ c)


def screw_axis(T: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float]:
    """The turn ``T`` (4, 4) as a screw: (a point of its axis, the one nearest the origin; its unit
    direction, the angle positive about it; the angle, degrees, in (0, 180]; the slide along the
    axis, mm). Undefined for a turn under a few hundredths of a degree."""
    from scipy.spatial.transform import Rotation

    rotvec = Rotation.from_matrix(T[:3, :3]).as_rotvec()
    angle = float(np.linalg.norm(rotvec))
    if angle < 1e-6:
        raise ValueError("no turn: the axis of an identity rotation is undefined")
    d = rotvec / angle
    t = T[:3, 3]
    slide = float(t @ d)
    # (I - R) c = t - slide d, with c perpendicular to d: least squares (I - R is singular along d)
    A = np.vstack([np.eye(3) - T[:3, :3], d[None]])
    b = np.concatenate([t - slide * d, [0.0]])
    c = np.linalg.lstsq(A, b, rcond=None)[0]
    return c, d, float(np.degrees(angle)), slide


def screw_axis_as(T: np.ndarray, direction, angle_deg: float, point_mm=None) -> tuple[np.ndarray, np.ndarray, float, float]:
    """``screw_axis(T)`` told as a given turn is (``direction``, ``angle_deg``): the direction
    flipped to point its way (the angle and slide with it), the angle within 180 deg of it, and
    the point the one nearest ``point_mm`` (when given) along the axis."""
    point, d, angle, slide = screw_axis(T)
    if d @ np.asarray(direction, float) < 0:
        d, angle, slide = -d, -angle, -slide
    angle += 360.0 * round((angle_deg - angle) / 360.0)
    if point_mm is not None:
        point = point + ((np.asarray(point_mm, float) - point) @ d) * d
    return point, d, angle, slide
