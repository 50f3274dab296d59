"""Registration graph: passes are nodes, matched target pairs are edges; all pass poses are
solved together by non-linear least squares (one pass held fixed), as in the paper.

The graph is plain data; solving is a pure function from graph to poses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial.transform import Rotation

from tasks.frames import apply_each

__all__ = ["RegistrationGraph", "RegistrationResult", "RegistrationError", "solve_pass_poses"]


class RegistrationError(ValueError):
    """Some passes cannot be registered (not connected to the fixed pass by target pairs)."""

    def __init__(self, message: str, unregistered: list[int], weak_pairs: list | None = None) -> None:
        super().__init__(message)
        self.unregistered = unregistered
        self.weak_pairs = weak_pairs or []


@dataclass(frozen=True)
class RegistrationGraph:
    """``edge_passes`` (e, 2) int: the two passes of each target pair; ``points_a``/``points_b``
    (e, 3) mm: the target centre as each pass saw it, in that pass's initial frame;
    ``T_initial`` (n, 4, 4): each pass's initial pose in the common frame."""

    n_passes: int
    edge_passes: np.ndarray
    points_a: np.ndarray
    points_b: np.ndarray
    T_initial: np.ndarray

    def __post_init__(self) -> None:
        e = len(self.edge_passes)
        if self.edge_passes.shape != (e, 2) or self.points_a.shape != (e, 3) or self.points_b.shape != (e, 3):
            raise ValueError("edge_passes (e, 2), points_a (e, 3) and points_b (e, 3) must agree")
        if self.T_initial.shape != (self.n_passes, 4, 4):
            raise ValueError(f"T_initial must have shape ({self.n_passes}, 4, 4)")
        if e and (self.edge_passes.min() < 0 or self.edge_passes.max() >= self.n_passes):
            raise ValueError("edge_passes refers to a pass that does not exist")


@dataclass(frozen=True)
class RegistrationResult:
    """``T_common_initial`` (n, 4, 4): maps each pass's initial frame into the common frame
    (the fixed pass's); ``residual_mm`` (e,) per target pair after the solve; ``inlier`` (e,)
    the pairs used; per-pass RMS of its pairs' residuals."""

    T_common_initial: np.ndarray
    residual_mm: np.ndarray
    inlier: np.ndarray
    pass_rms_mm: np.ndarray
    fixed: int
    iterations: int


def _poses(x: np.ndarray, free: np.ndarray, centres: np.ndarray, n: int) -> np.ndarray:
    T = np.repeat(np.eye(4)[None], n, axis=0)
    params = x.reshape(-1, 6)
    R = Rotation.from_rotvec(params[:, :3]).as_matrix()
    T[free, :3, :3] = R
    T[free, :3, 3] = centres[free] + params[:, 3:] - np.einsum("nij,nj->ni", R, centres[free])
    return T


def _connected(n: int, edges: np.ndarray, fixed: int) -> np.ndarray:
    if len(edges) == 0:
        reach = np.zeros(n, bool)
        reach[fixed] = True
        return reach
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    return labels == labels[fixed]


def solve_pass_poses(graph: RegistrationGraph, *, fixed: int = 0, outlier_mm: float = 0.3,
                     names: list[str] | None = None) -> RegistrationResult:
    """Solve every pass's pose from the target pairs; pairs off by more than ``outlier_mm`` (or
    five times the median residual) after a first solve are dropped and the solve repeated."""
    n = graph.n_passes
    if not 0 <= fixed < n:
        raise ValueError(f"fixed pass {fixed} out of range 0..{n - 1}")
    reach = _connected(n, graph.edge_passes, fixed)
    if not reach.all():
        lost = [int(i) for i in np.flatnonzero(~reach)]
        label = [names[i] for i in lost] if names else lost
        raise RegistrationError(f"passes {label} share no chain of 3+ common targets with the others; "
                                "they cannot be registered", lost)
    a = apply_each(graph.T_initial[graph.edge_passes[:, 0]], graph.points_a)
    b = apply_each(graph.T_initial[graph.edge_passes[:, 1]], graph.points_b)
    centres = np.zeros((n, 3))
    for k in range(n):
        pts = np.concatenate([a[graph.edge_passes[:, 0] == k], b[graph.edge_passes[:, 1] == k]])
        centres[k] = pts.mean(axis=0) if len(pts) else 0.0
    free = np.flatnonzero(np.arange(n) != fixed)
    inlier = np.ones(len(a), bool)
    x = np.zeros(6 * len(free))
    iterations = 0
    for _ in range(3):
        ea, eb, pa, pb = graph.edge_passes[inlier, 0], graph.edge_passes[inlier, 1], a[inlier], b[inlier]

        def residuals(x: np.ndarray) -> np.ndarray:
            T = _poses(x, free, centres, n)
            return (apply_each(T[ea], pa) - apply_each(T[eb], pb)).ravel()

        sol = least_squares(residuals, x, method="trf", x_scale="jac")
        x, iterations = sol.x, iterations + sol.nfev
        T = _poses(x, free, centres, n)
        res = np.linalg.norm(apply_each(T[graph.edge_passes[:, 0]], a) - apply_each(T[graph.edge_passes[:, 1]], b), axis=1)
        limit = max(outlier_mm, 5 * float(np.median(res[inlier]))) if inlier.any() else outlier_mm  # a lone pass: none
        new = res <= limit
        if np.array_equal(new, inlier):
            break
        inlier = new
        if not _connected(n, graph.edge_passes[inlier], fixed).all():
            inlier = np.ones(len(a), bool) if not inlier.any() else inlier | (res <= 2 * limit)
    T = _poses(x, free, centres, n) @ graph.T_initial
    pass_rms = np.array([np.sqrt(np.mean(res[inlier & np.any(graph.edge_passes == k, axis=1)] ** 2))
                         if np.any(inlier & np.any(graph.edge_passes == k, axis=1)) else np.nan for k in range(n)])
    return RegistrationResult(T_common_initial=T, residual_mm=res, inlier=inlier, pass_rms_mm=pass_rms,
                              fixed=fixed, iterations=iterations)
