"""Joint refinement of all pass poses on targets *and* overlapping surfaces.

The paper registers on sticker centres alone. Those carry ~30 um of error each, and a strip-shaped
pass is held by a few stickers near its middle, so its tilt is poorly known and its ends swing
(measured: up to ~0.17 mm). Overlapping passes measured the same surface, though, thousands of
points each: point-to-plane distances between them fix exactly the directions targets leave
loose (tilt, height), while the targets keep fixing the directions a flat surface cannot
(sliding along it, turning about its normal).

One Gauss-Newton problem over every pass pose (one held fixed) with two kinds of residuals:

- target pairs: ``(T_a p_a - T_b p_b) / target_sigma_mm`` (3 rows each, as in registration);
- surface pairs: for thinned points p of pass a, the nearest measured point q of an overlapping
  pass b, ``n_b . (T_a p - T_b q) / surface_sigma_mm`` (1 row each), Huber-weighted; both ways
  round for every pair; dropped beyond the gate, where the two normals disagree, or where either
  neighbourhood is curved (a weld toe): point-to-plane distances there are biased by the
  curvature, and that bias, summed over thousands of points, turned passes by ~0.15 mrad in a
  test where identical surfaces and exact targets should have given none.

Correspondences are found again every iteration, the gate shrinking from ``max_distance_mm`` to
``final_distance_mm``. All of it is plain numpy/scipy: KD-trees per pass in the pass's own frame
(built once), a sparse Jacobian, normal equations of 6(n-1) unknowns.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from tasks.arrays import distinct
from tasks.cells import ReachGrid, first_in_each_cell
from tasks.checks import check_points
from tasks.frames import apply

__all__ = ["NothingToRefine", "SurfaceSample", "RefineResult", "orient_toward", "surface_sample", "refine_poses"]


class NothingToRefine(ValueError):
    """An iteration of ``refine_poses`` found no residual at all: no target pairs, and no two
    passes with 50 or more surface correspondences within the gate."""


@dataclass(frozen=True)
class SurfaceSample:
    """One pass's surface in the pass's own (coarse) frame: ``points_mm`` (m, 3), a thinned set
    with unit ``normals`` (m, 3), matched against the other passes; ``dense_mm`` (k, 3) all its
    points, which the other passes are matched against; ``tree`` a k-d tree of ``dense_mm``
    (built here when not given); ``view_direction`` (3,) toward the sensor, or None. Normals are
    turned toward a pass's view direction, and where both passes of a pair have one, a match
    needs ``n_a . n_b >= min_normal_cos``: the front and back of a thin part (an ear, a sheet)
    never match, which unoriented normals (``|n_a . n_b|``, None) allow within the gate."""

    points_mm: np.ndarray
    normals: np.ndarray
    dense_mm: np.ndarray
    tree: cKDTree | None = None
    view_direction: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.tree is None and len(self.dense_mm):
            object.__setattr__(self, "tree", cKDTree(self.dense_mm))


@dataclass(frozen=True)
class RefineResult:
    """``T_common_pass`` (n, 4, 4) refined poses; ``pair_rms_mm`` {(a, b): point-to-plane RMS of
    the pair's accepted correspondences}; ``pair_count`` {(a, b): how many}; ``target_residual_mm``
    (e,) per target pair after refinement; ``step_mm`` the largest point move of each iteration,
    over the passes' extents."""

    T_common_pass: np.ndarray
    pair_rms_mm: dict
    pair_count: dict
    target_residual_mm: np.ndarray
    step_mm: list[float]


def orient_toward(normals: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Unit normals (k, 3), each turned (sign flipped) to point toward ``direction`` (3,) (the sensor)."""
    return normals * np.where(normals @ direction < 0, -1.0, 1.0)[:, None]


def surface_sample(grid_mm: np.ndarray, *, spacing_mm: float, normal_radius_mm: float,
                   neighbours: int, max_plane_rms_mm: float, view_direction: np.ndarray | None = None) -> SurfaceSample:
    """Thin a pass's points ((..., 3); NaN rows where nothing was measured) to the first point in
    each ``spacing_mm`` cube, with a normal from the plane through its ``neighbours`` nearest
    points of the whole pass (PCA); points whose neighbours reach beyond ``normal_radius_mm``
    (edges, stray points) are dropped, and so are points whose neighbours stray from their plane
    by more than ``max_plane_rms_mm`` (RMS): on a curved patch (a weld toe) a point-to-plane
    distance is biased by the curvature, and that bias would steer the poses. ``view_direction``
    (3,), toward the sensor in the pass's frame: the normals are oriented (see SurfaceSample)."""
    if view_direction is not None:
        view_direction = np.asarray(view_direction, dtype=np.float64)
        if view_direction.shape != (3,) or not np.isfinite(view_direction).all() or not np.any(view_direction):
            raise ValueError(f"view_direction must be a finite non-zero (3,) vector, got {view_direction!r}")
    pts = np.asarray(grid_mm, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) < neighbours:
        return SurfaceSample(np.zeros((0, 3)), np.zeros((0, 3)), pts, view_direction=view_direction)
    first = first_in_each_cell(np.floor(pts / spacing_mm).astype(np.int64))
    tree = cKDTree(pts)
    planes = _planes_at(pts, tree, first, neighbours)
    # a full neighbourhood close by (not an edge or a lone point), and a flat one
    keep = (planes[:, 6] <= normal_radius_mm) & (planes[:, 7] <= max_plane_rms_mm)
    normals = planes[keep, 3:6]
    if view_direction is not None:
        normals = orient_toward(normals, view_direction)
    return SurfaceSample(pts[first[keep]], normals, pts, tree, view_direction)


def _matched(src: np.ndarray, order: np.ndarray, tree: cKDTree, occupied: ReachGrid, *,
             most: int) -> tuple[np.ndarray, np.ndarray]:
    """The source points ``src`` (m, 3) that have a point of ``tree`` within ``occupied.reach_mm``,
    at most ``most`` of them, the first in ``order`` (a permutation of range(m)): their indices,
    ascending, and their nearest tree points. Only points that ``occupied`` says may reach one are
    searched, and the search stops once ``most`` are found: the answer is that of querying every
    point and keeping the first ``most`` found, for a fraction of the queries."""
    candidates = order[occupied.may_reach(src)[order]]
    found_src, found_nearest, count = [], [], 0
    chunk = 2 * most
    for start in range(0, len(candidates), chunk):
        part = candidates[start:start + chunk]
        dist, nearest = tree.query(src[part], distance_upper_bound=occupied.reach_mm, workers=1)
        hit = np.isfinite(dist)
        found_src.append(part[hit])
        found_nearest.append(nearest[hit])
        count += int(hit.sum())
        if count >= most:
            break
    if not found_src:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    chosen = np.concatenate(found_src)[:most]
    nearest = np.concatenate(found_nearest)[:most]
    ascending = np.argsort(chosen)
    return chosen[ascending], nearest[ascending]


def _planes_at(dense: np.ndarray, tree: cKDTree, idx: np.ndarray, k: int) -> np.ndarray:
    """The local plane at dense points ``idx`` (PCA of the k nearest dense points): (m, 8) of
    centroid (3), unit normal (3), neighbourhood radius, RMS distance from the plane.

    The plane passes through the neighbourhood's centroid, not through the matched point: the
    matched point's own noise also tilts the fitted normal, and a residual measured from that
    point correlates with the normal's tilt, which pushed a test's passes 60 urad about their
    normals (targets exact, surfaces unbiased); from the centroid it does not."""
    dist, nn = tree.query(dense[idx], k=k, workers=1)
    local = dense[nn]
    centroid = local.mean(axis=1)
    local -= centroid[:, None, :]
    values, vectors = np.linalg.eigh(np.einsum("kni,knj->kij", local, local))
    return np.column_stack([centroid, vectors[:, :, 0], dist[:, -1], np.sqrt(np.maximum(values[:, 0], 0) / k)])


def _skew_rows(v: np.ndarray) -> np.ndarray:
    """(k, 3) -> (k, 3, 3): d(w x v)/dw = -[v]x."""
    out = np.zeros((len(v), 3, 3))
    out[:, 0, 1], out[:, 0, 2] = v[:, 2], -v[:, 1]
    out[:, 1, 0], out[:, 1, 2] = -v[:, 2], v[:, 0]
    out[:, 2, 0], out[:, 2, 1] = v[:, 1], -v[:, 0]
    return out


def _overlapping_pairs(boxes: np.ndarray, margin: float) -> list[tuple[int, int]]:
    n = len(boxes)
    return [(a, b) for a in range(n) for b in range(a + 1, n)
            if np.all(boxes[a, 0] - margin <= boxes[b, 1]) and np.all(boxes[b, 0] - margin <= boxes[a, 1])]


def _priority(normals: np.ndarray, *, seed: int, normal_space: bool) -> np.ndarray:
    """The order in which a pass's thinned points are taken when a pair has more than it may use
    (lower first): random, or with ``normal_space`` round-robin over bins of normal direction
    (normal-space sampling, Rusinkiewicz & Levoy 2001): the few points on slopes (weld cap, edges)
    that hold a pass against sliding on the plate are taken before more of the plate."""
    m = len(normals)
    order = np.random.default_rng(seed).permutation(m)
    if not normal_space or m == 0:
        return order
    up = np.median(normals, axis=0)
    up /= max(np.linalg.norm(up), 1e-12)
    n = normals * np.where(normals @ up < 0, -1.0, 1.0)[:, None]
    tilt = np.degrees(np.arccos(np.clip(n @ up, -1.0, 1.0)))
    e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    azimuth = np.degrees(np.arctan2(n @ e2, n @ e1)) % 360.0
    bins = np.where(tilt < 5.0, 0, 1 + np.minimum(tilt // 5.0, 8).astype(np.int64) * 8 + (azimuth // 45.0).astype(np.int64))
    # rank within bin by the random order; then round-robin over the bins
    by = np.lexsort((order, bins))
    rank = np.empty(m, np.int64)
    starts = np.flatnonzero(np.r_[True, bins[by][1:] != bins[by][:-1]])
    counts = np.diff(np.r_[starts, m])
    rank[by] = np.arange(m) - np.repeat(starts, counts)
    return rank * m + order


def refine_poses(samples: list[SurfaceSample], T_common_pass: np.ndarray, edge_passes: np.ndarray,
                 points_a: np.ndarray, points_b: np.ndarray, *, max_iterations: int, tolerance_mm: float,
                 max_distance_mm: float, final_distance_mm: float, neighbour_mm: float, normal_neighbours: int,
                 target_sigma_mm: float | np.ndarray, surface_sigma_mm: float, max_points_per_pair: int, min_normal_cos: float,
                 max_plane_rms_mm: float, normal_space: bool, fixed: int = 0, free: Sequence[int] | None = None,
                 warm: bool = False) -> RefineResult:
    """Refine ``T_common_pass`` (n, 4, 4; pass frame -> common frame, from target registration).

    ``edge_passes`` (e, 2), ``points_a``/``points_b`` (e, 3): the inlier target pairs, each centre
    in its own pass's frame. A surface correspondence needs a dense point of the other pass
    within ``neighbour_mm``, whose ``normal_neighbours`` nearest points lie within
    ``neighbour_mm`` and within ``max_plane_rms_mm`` of their plane, with a normal within
    ``acos(min_normal_cos)`` of the source point's; each pair contributes at most
    ``max_points_per_pair`` per direction. Returns the refined poses; pass ``fixed`` does not move.

    A problem that grows with the scan: ``free`` (pass indices) the only passes that move, the
    others held where ``T_common_pass`` puts them (a solved problem's poses), and only the target
    and surface pairs that touch a free pass counted (the others' residuals cannot change);
    ``fixed`` is then unread. ``warm``: the poses are already close (a solved problem, a pass
    added to it): every iteration at ``final_distance_mm`` instead of narrowing to it from
    ``max_distance_mm``. Raises ``NothingToRefine`` (a ValueError) when an iteration finds no
    residual at all.
    """
    n = len(samples)
    T = np.array(T_common_pass, dtype=np.float64)
    if T.shape != (n, 4, 4) or not np.isfinite(T).all():
        raise ValueError(f"T_common_pass must be finite with shape ({n}, 4, 4), got {T.shape}")
    edge_passes = np.asarray(edge_passes, dtype=np.int64).reshape(-1, 2)
    points_a = check_points("points_a", points_a) if len(edge_passes) else np.zeros((0, 3))
    points_b = check_points("points_b", points_b) if len(edge_passes) else np.zeros((0, 3))
    trees = [s.tree if len(s.dense_mm) >= normal_neighbours else None for s in samples]
    if free is None:
        moving = np.arange(n) != fixed
    else:
        free = np.asarray(free, dtype=np.int64).reshape(-1)
        if len(free) == 0 or len(free) >= n or free.min() < 0 or free.max() >= n:
            raise ValueError(f"free must name 1 to {n - 1} of the {n} passes (0..{n - 1}), got {free.tolist()}")
        moving = np.isin(np.arange(n), free)
    free = np.flatnonzero(moving)
    pair_sigma = np.asarray(target_sigma_mm, dtype=np.float64)
    if pair_sigma.ndim:  # each pair its own
        if pair_sigma.shape != (len(edge_passes),) or not (np.isfinite(pair_sigma).all() and (pair_sigma > 0).all()):
            raise ValueError(f"target_sigma_mm must be one positive value or one per target pair "
                             f"({len(edge_passes)}), got shape {pair_sigma.shape}")
    all_pairs = edge_passes, points_a, points_b  # every pair's residual is returned
    if len(edge_passes):  # a pair of two held passes adds a constant: left out
        touching = moving[edge_passes].any(axis=1)
        edge_passes, points_a, points_b = edge_passes[touching], points_a[touching], points_b[touching]
        if pair_sigma.ndim:
            pair_sigma = pair_sigma[touching]
    sigma_rows = pair_sigma[:, None] if pair_sigma.ndim else pair_sigma  # per pair's three rows, or one for all
    column = np.full(n, -1)
    column[free] = np.arange(len(free))
    # the pose increment rotates about this centre, which keeps the normal equations well scaled
    centre = np.mean([apply(T[k], s.points_mm).mean(axis=0) for k, s in enumerate(samples) if len(s.points_mm)], axis=0)
    # the gate on point-to-plane distances narrows over the first iterations, then stays; the
    # loop ends once no pass point moves more than tolerance_mm
    gates = [] if warm else np.geomspace(max_distance_mm, final_distance_mm, 3).tolist()
    gates += [final_distance_mm] * max(max_iterations - len(gates), 0)
    gates = gates[:max_iterations]
    cache = [np.full((len(s.dense_mm), 8), np.nan) for s in samples]
    occupied = [ReachGrid(s.dense_mm, neighbour_mm) if tree is not None else None for s, tree in zip(samples, trees)]
    # each pass's points in the order they are taken, when a pair has more than it may use: by a
    # fixed priority, the same points every iteration
    by_priority = [np.argsort(_priority(s.normals, seed=k, normal_space=normal_space), kind="stable")
                   for k, s in enumerate(samples)]

    def planes(k: int, idx: np.ndarray) -> np.ndarray:
        """Local planes at pass k's dense points idx (see _planes_at), each computed once."""
        todo = distinct(idx[np.isnan(cache[k][idx, 0])])
        if len(todo):
            cache[k][todo] = _planes_at(samples[k].dense_mm, trees[k], todo, normal_neighbours)
            if samples[k].view_direction is not None:  # oriented toward the pass's sensor
                cache[k][todo, 3:6] = orient_toward(cache[k][todo, 3:6], samples[k].view_direction)
        return cache[k][idx]

    steps: list[float] = []
    pair_rms: dict = {}
    pair_count: dict = {}
    for gate in gates:
        rows_j, rows_r = [], []  # per residual block: (k, 12) jacobian wrt (pose a, pose b), (k,) residual
        blocks_ab = []
        boxes = np.array([[apply(T[k], s.points_mm).min(axis=0), apply(T[k], s.points_mm).max(axis=0)]
                          if len(s.points_mm) else [[np.inf] * 3, [-np.inf] * 3] for k, s in enumerate(samples)])
        pair_rms, pair_count = {}, {}
        # both ways round: point-to-plane on a curved surface is biased (the tangent plane at the
        # matched point passes outside a convex surface), and the two directions cancel that
        for a, b in [p for pair in _overlapping_pairs(boxes, gate) if moving[list(pair)].any() for p in (pair, pair[::-1])]:
            sa, tree_b = samples[a], trees[b]
            if tree_b is None or len(sa.points_mm) == 0:
                continue
            T_b_a = np.linalg.solve(T[b], T[a])
            src_idx, nearest = _matched(apply(T_b_a, sa.points_mm), by_priority[a], tree_b, occupied[b],
                                        most=max_points_per_pair)
            if len(src_idx) < 50:
                continue
            plane = planes(b, nearest)
            n_b, reach, plane_rms = plane[:, 3:6], plane[:, 6], plane[:, 7]
            n_a_in_b = sa.normals[src_idx] @ T_b_a[:3, :3].T
            cos = np.einsum("ij,ij->i", n_a_in_b, n_b)
            if sa.view_direction is None or samples[b].view_direction is None:
                cos = np.abs(cos)  # unoriented normals
            ok = ((cos >= min_normal_cos) & (reach <= neighbour_mm)
                  & (plane_rms <= max_plane_rms_mm))
            src_idx, n_b, q_b = src_idx[ok], n_b[ok], plane[ok, :3]
            P = apply(T[a], sa.points_mm[src_idx]) - centre
            Q = apply(T[b], q_b) - centre
            N = n_b @ T[b][:3, :3].T
            r = np.einsum("ij,ij->i", N, P - Q)
            close = np.abs(r) <= gate
            P, Q, N, r = P[close], Q[close], N[close], r[close]
            if len(r) < 50:
                continue
            # Huber weights at 2 sigma
            scale = np.abs(r) / (2 * surface_sigma_mm)
            w = np.where(scale > 1, 1 / np.sqrt(np.maximum(scale, 1)), 1.0) / surface_sigma_mm
            J = np.concatenate([np.cross(P, N), N, -np.cross(Q, N), -N], axis=1) * w[:, None]
            rows_j.append(J)
            rows_r.append(r * w)
            blocks_ab.append(np.repeat([[a, b]], len(r), axis=0))
            pair_rms[(a, b)] = float(np.sqrt(np.mean(r ** 2)))
            pair_count[(a, b)] = len(r)
        if len(edge_passes):
            P = np.einsum("nij,nj->ni", T[edge_passes[:, 0], :3, :3], points_a) + T[edge_passes[:, 0], :3, 3] - centre
            Q = np.einsum("nij,nj->ni", T[edge_passes[:, 1], :3, :3], points_b) + T[edge_passes[:, 1], :3, 3] - centre
            r = (P - Q) / sigma_rows
            eye = np.broadcast_to(np.eye(3), (len(P), 3, 3))
            J = np.concatenate([_skew_rows(P), eye, -_skew_rows(Q), -eye], axis=2) / (
                sigma_rows[:, :, None] if pair_sigma.ndim else sigma_rows)
            rows_j.append(J.reshape(-1, 12))
            rows_r.append(r.reshape(-1))
            blocks_ab.append(np.repeat(edge_passes, 3, axis=0))
        if not rows_j:
            raise NothingToRefine(f"nothing to refine: no target pairs, and no two passes with 50 or more surface "
                                  f"correspondences within {gate:.3g} mm")
        J = np.concatenate(rows_j)
        res = np.concatenate(rows_r)
        ab = np.concatenate(blocks_ab)
        # scatter the (k, 12) blocks into the (k, 6 * free) sparse Jacobian, dropping the fixed pass
        cols = np.concatenate([6 * column[ab[:, 0], None] + np.arange(6), 6 * column[ab[:, 1], None] + np.arange(6)],
                              axis=1)
        keep = cols >= 0
        row_index = np.broadcast_to(np.arange(len(J))[:, None], cols.shape)
        A = sparse.csr_matrix((J[keep], (row_index[keep], cols[keep])), shape=(len(J), 6 * len(free)))
        H = (A.T @ A).toarray()
        g = A.T @ res
        H[np.diag_indices_from(H)] += 1e-9 * max(np.trace(H) / len(H), 1.0)
        dx = -np.linalg.solve(H, g).reshape(-1, 6)
        step = 0.0
        for c, k in enumerate(free):
            R = Rotation.from_rotvec(dx[c, :3]).as_matrix()
            D = np.eye(4)
            D[:3, :3] = R
            D[:3, 3] = centre + dx[c, 3:] - R @ centre
            if len(samples[k].points_mm):
                moved = apply(T[k], samples[k].points_mm)
                step = max(step, float(np.linalg.norm(apply(D, moved) - moved, axis=1).max()))
            T[k] = D @ T[k]
        steps.append(step)
        if gate == final_distance_mm and step < tolerance_mm:
            break
    edge_passes, points_a, points_b = all_pairs
    target_res = (np.linalg.norm(np.einsum("nij,nj->ni", T[edge_passes[:, 0], :3, :3], points_a) + T[edge_passes[:, 0], :3, 3]
                                 - np.einsum("nij,nj->ni", T[edge_passes[:, 1], :3, :3], points_b)
                                 - T[edge_passes[:, 1], :3, 3], axis=1) if len(edge_passes) else np.zeros(0))
    return RefineResult(T_common_pass=T, pair_rms_mm=pair_rms, pair_count=pair_count,
                        target_residual_mm=target_res, step_mm=steps)
