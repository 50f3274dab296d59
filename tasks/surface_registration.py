"""Registration of scans on their surfaces alone: no stickers, and with or without rough poses.

Three uses, one machinery:

- rough poses given (a robot log, a lab's alignment, perturbed): ``refine_scan_poses``, the
  project's joint Gauss-Newton over all poses (``tasks.refine.refine_poses``, no target pairs),
  run coarse to fine: the point-to-plane gate shrinks level by level (``RefineOptions.gates_mm``),
  so a start 5 mm / 5 degrees off converges;
- no poses at all, two scans: ``register_pair``. FPFH features (Open3D) on a voxel grid, each
  keypoint matched to its nearest descriptor in the other scan, both ways; RANSAC over triples
  of matches (edge lengths must agree; Kabsch), here in numpy with a seeded generator; the
  best-supported *distinct* hypotheses each refined by point-to-plane ICP (``refine_scan_poses``
  on the two scans). A pose is accepted only on evidence measured after ICP, on the surfaces,
  not on the features: the overlap (``fitness``: the share of surface samples with a measured
  point of the other scan within ``inlier_mm``), the point-to-plane RMS of the matches, and the
  margin over the runner-up, the best refined pose that is clearly different, sought among the
  other hypotheses and from six starts around the best (shifted along the overlap, turned about
  its normal). When the runner-up scores nearly as well (a plate sliding on a plate, a repeating
  pattern, a body of revolution turning about its axis) the pair is ambiguous and refused, with
  the figures in ``reason``;
- no poses at all, many scans: ``register_scans``. Every pair as above; a maximum spanning tree
  of the accepted pairs, weighted by their overlap; poses chained from the reference scan along
  it; then all poses refined jointly on every overlapping surface. A scan with no chain of
  accepted pairs to the reference is refused (NaN pose), never guessed.

Frames: each scan's points are in its own (sensor) frame; ``T_world_scan`` (4, 4) maps them to
the common frame of the reference scan (``fixed``), ``T_target_source`` maps a source scan's
points into the target scan's frame. Units: mm. Normals are oriented toward each scan's sensor
(``view_direction``), so the front and back of a thin part never match.

Deterministic: the same points and options give the same bytes on every run and thread count.
Open3D's own RANSAC (``registration_ransac_based_on_feature_matching``) is not: with a fixed
``o3d.utility.random.seed`` it returned one of two poses for the same bunny pairs in six
processes (OpenMP threads race to the best hypothesis and its early stop), so the hypotheses
are drawn here with numpy; FPFH and normals are computed per point (no sums across points) and
the refinement is numpy with one-worker k-d tree queries.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from tasks.cells import first_in_each_cell
from tasks.checks import check_points
from tasks.frames import apply
from tasks.matching import pose_difference
from tasks.refine import NothingToRefine, RefineResult, SurfaceSample, orient_toward, refine_poses, surface_sample

__all__ = ["ScanFeatures", "RefineOptions", "PairOptions", "PairRegistration", "ScanRegistration",
           "scan_features", "refine_scan_poses", "register_pair", "register_scans"]


@dataclass(frozen=True)
class ScanFeatures:
    """One scan, in its own frame: ``keypoints_mm`` (m, 3) one point per ``voxel_mm`` cube, their
    unit ``normals`` (m, 3) turned toward the sensor, ``fpfh`` (m, 33) their FPFH descriptors;
    ``surface`` the scan's thinned points with normals and all its points (``tasks.refine``)."""

    keypoints_mm: np.ndarray
    normals: np.ndarray
    fpfh: np.ndarray
    surface: SurfaceSample
    voxel_mm: float


@dataclass(frozen=True, kw_only=True)
class RefineOptions:
    """The surface refinement (``tasks.refine.refine_poses``), coarse to fine. ``gates_mm``:
    point-to-plane gates, descending, one level each (the first must exceed the largest start
    error of a point); ``neighbour_mm``: the least search radius for a matched point, and how far
    a point's ``normal_neighbours`` nearest may reach (above the scans' point spacing);
    ``max_plane_rms_mm``: neighbourhoods straying more from their plane are not matched (above the
    scanner's noise); ``surface_sigma_mm``: a match's expected error (Huber at twice it); at most
    ``iterations_per_level`` Gauss-Newton steps per level, the last level ending once no point
    moves more than ``tolerance_mm``."""

    gates_mm: tuple[float, ...]
    neighbour_mm: float
    max_plane_rms_mm: float
    surface_sigma_mm: float
    min_normal_cos: float
    normal_neighbours: int
    max_points_per_pair: int
    iterations_per_level: int
    tolerance_mm: float

    def __post_init__(self) -> None:
        gates = np.asarray(self.gates_mm, dtype=np.float64)
        if gates.ndim != 1 or len(gates) == 0 or not np.all(gates > 0) or np.any(np.diff(gates) > 0):
            raise ValueError(f"gates_mm must be positive and descending, got {self.gates_mm}")
        for name in ("neighbour_mm", "max_plane_rms_mm", "surface_sigma_mm", "tolerance_mm"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not 0 < self.min_normal_cos <= 1:
            raise ValueError(f"min_normal_cos must be in (0, 1], got {self.min_normal_cos}")


@dataclass(frozen=True, kw_only=True)
class PairOptions:
    """Global registration of a pair. ``draws`` RANSAC triples from generator ``seed``, a match
    an inlier within ``ransac_inlier_mm``; the ``top_k`` best-supported hypotheses that differ by
    more than ``distinct_deg`` or move the source's centroid more than ``distinct_mm`` are each
    refined; accepted when the best has ``fitness >= min_fitness`` (share of surface samples
    within ``inlier_mm`` of the other scan, the better of the two directions), an RMS
    ``<= max_rms_mm``, and no distinct refined pose with a passing RMS scores
    ``>= max_runner_up_ratio`` of its fitness. Matches: each keypoint's nearest descriptor, both
    ways; ``mutual_only``: only pairs that are each other's nearest (fewer, cleaner; too few on
    repetitive surfaces to find the alternatives there)."""

    ransac_inlier_mm: float
    inlier_mm: float
    max_rms_mm: float
    distinct_mm: float
    distinct_deg: float = 10.0
    min_fitness: float = 0.25
    max_runner_up_ratio: float = 0.7
    draws: int = 20000
    top_k: int = 4
    seed: int = 0
    mutual_only: bool = False

    def __post_init__(self) -> None:
        for name in ("ransac_inlier_mm", "inlier_mm", "max_rms_mm", "distinct_mm", "distinct_deg"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not (0 < self.min_fitness <= 1 and 0 < self.max_runner_up_ratio <= 1):
            raise ValueError(f"min_fitness and max_runner_up_ratio must be in (0, 1], got {self.min_fitness}, "
                             f"{self.max_runner_up_ratio}")
        if self.draws < 1 or self.top_k < 1:
            raise ValueError(f"draws and top_k must be >= 1, got {self.draws}, {self.top_k}")


@dataclass(frozen=True)
class PairRegistration:
    """``T_target_source`` (4, 4) the best refined pose; ``accepted``, and ``reason`` (why not,
    with the figures; empty when accepted). Evidence: ``fitness`` and ``rms_mm`` of the best,
    ``runner_up_fitness`` and ``runner_up_rms_mm`` of the best refined pose distinct from it
    (0 and NaN when every hypothesis converged to the best), and how far that one is
    (``runner_up_deg``, ``runner_up_mm`` at the source's centroid); ``matches`` feature matches,
    ``ransac_support`` of them agreeing with the best hypothesis before refinement (0 when the
    best came from a start around another hypothesis)."""

    source: int
    target: int
    T_target_source: np.ndarray
    accepted: bool
    reason: str
    fitness: float
    rms_mm: float
    runner_up_fitness: float
    runner_up_rms_mm: float
    runner_up_deg: float
    runner_up_mm: float
    matches: int
    ransac_support: int


@dataclass(frozen=True)
class ScanRegistration:
    """``T_world_scan`` (n, 4, 4) scan frame -> the reference scan's frame, NaN where a scan is
    refused; ``registered`` (n,) bool; ``method`` per scan: "reference", "surfaces" (chained
    along verified pairs, then refined) or "refused"; ``reason`` per scan (empty unless refused);
    ``pairs`` every pair tried; ``tree`` (m, 2) the (parent, child) pairs the poses were chained
    along; ``refine`` the joint refinement (None when nothing was left to refine)."""

    T_world_scan: np.ndarray
    registered: np.ndarray
    method: tuple[str, ...]
    reason: tuple[str, ...]
    pairs: tuple[PairRegistration, ...]
    tree: np.ndarray
    refine: RefineResult | None


def scan_features(points_mm: np.ndarray, *, view_direction: np.ndarray, voxel_mm: float, sample_spacing_mm: float,
                  neighbour_mm: float, max_plane_rms_mm: float, normal_neighbours: int) -> ScanFeatures:
    """Features of one scan. ``points_mm`` (..., 3) float, mm, in the scan's frame (an organized
    grid may hold NaN rows where nothing was measured); ``view_direction`` (3,) from the surface
    toward the sensor, in the same frame (normals are turned toward it). Keypoints: the first
    point in each ``voxel_mm`` cube, normals from their neighbours within 2 voxels, FPFH over 5
    voxels. ``surface``: ``tasks.refine.surface_sample`` at ``sample_spacing_mm``."""
    pts = np.asarray(points_mm, dtype=np.float64)
    if pts.ndim < 2 or pts.shape[-1] != 3:
        raise ValueError(f"points_mm must have shape (n, 3) or (rows, cols, 3), got {pts.shape}")
    pts = pts.reshape(-1, 3)
    pts = check_points("points_mm", pts[np.isfinite(pts).all(axis=1)])
    view = np.asarray(view_direction, dtype=np.float64)
    if view.shape != (3,) or not np.isfinite(view).all() or np.linalg.norm(view) == 0:
        raise ValueError(f"view_direction must be a finite non-zero (3,) vector, got {view_direction!r}")
    if not (voxel_mm > 0 and sample_spacing_mm > 0):
        raise ValueError(f"voxel_mm and sample_spacing_mm must be > 0, got {voxel_mm}, {sample_spacing_mm}")
    keys = pts[first_in_each_cell(np.floor(pts / voxel_mm).astype(np.int64))]
    if len(keys) < 10:
        raise ValueError(f"points_mm gives {len(keys)} keypoints at voxel_mm {voxel_mm}; need 10 or more")
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(keys))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.0 * voxel_mm, max_nn=30))
    normals = np.asarray(cloud.normals).copy()
    normals = orient_toward(normals, view)
    cloud.normals = o3d.utility.Vector3dVector(normals)
    fpfh = o3d.pipelines.registration.compute_fpfh_feature(
        cloud, o3d.geometry.KDTreeSearchParamHybrid(radius=5.0 * voxel_mm, max_nn=100))
    surface = surface_sample(pts, spacing_mm=sample_spacing_mm, normal_radius_mm=neighbour_mm,
                             neighbours=normal_neighbours, max_plane_rms_mm=max_plane_rms_mm, view_direction=view)
    return ScanFeatures(keys, normals, np.asarray(fpfh.data).T.copy(), surface, float(voxel_mm))


def refine_scan_poses(surfaces: list[SurfaceSample], T_world_scan: np.ndarray, *, options: RefineOptions,
                      fixed: int = 0) -> RefineResult:
    """All poses ``T_world_scan`` (n, 4, 4) refined together on the scans' overlapping surfaces
    (``tasks.refine.refine_poses`` with no target pairs), one level per gate of
    ``options.gates_mm``; scan ``fixed`` does not move. The result's pair figures are the last
    level's, ``step_mm`` every iteration's. Raises ``tasks.refine.NothingToRefine`` when no two
    scans overlap within the first gate."""
    T = np.array(T_world_scan, dtype=np.float64)
    if T.shape != (len(surfaces), 4, 4) or not np.isfinite(T).all():
        raise ValueError(f"T_world_scan must be finite with shape ({len(surfaces)}, 4, 4), got {T.shape}")
    if not 0 <= fixed < len(surfaces):
        raise ValueError(f"fixed must index one of the {len(surfaces)} scans, got {fixed}")
    steps: list[float] = []
    result = None
    for gate in options.gates_mm:  # no target pairs (target_sigma_mm unused)
        result = refine_poses(surfaces, T, np.zeros((0, 2), np.int64), np.zeros((0, 3)), np.zeros((0, 3)),
                              max_iterations=options.iterations_per_level, tolerance_mm=options.tolerance_mm,
                              max_distance_mm=gate, final_distance_mm=gate,
                              neighbour_mm=max(gate, options.neighbour_mm), normal_neighbours=options.normal_neighbours,
                              target_sigma_mm=1.0, surface_sigma_mm=options.surface_sigma_mm,
                              max_points_per_pair=options.max_points_per_pair, min_normal_cos=options.min_normal_cos,
                              max_plane_rms_mm=options.max_plane_rms_mm, normal_space=False, fixed=fixed)
        T = result.T_common_pass
        steps += result.step_mm
    return RefineResult(T_common_pass=T, pair_rms_mm=result.pair_rms_mm, pair_count=result.pair_count,
                        target_residual_mm=result.target_residual_mm, step_mm=steps)


def _kabsch(P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """(h, k, 3) point sets -> (h, 4, 4) rigid transforms taking P onto Q in least squares."""
    cp, cq = P.mean(axis=1), Q.mean(axis=1)
    U, _, Vt = np.linalg.svd(np.einsum("hki,hkj->hij", P - cp[:, None], Q - cq[:, None]))
    d = np.sign(np.linalg.det(np.einsum("hji,hkj->hik", Vt, U)))
    R = np.einsum("hji,hj,hkj->hik", Vt, np.stack([np.ones_like(d), np.ones_like(d), d], axis=1), U)
    T = np.tile(np.eye(4), (len(P), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = cq - np.einsum("hij,hj->hi", R, cp)
    return T


def _distinct(T1: np.ndarray, T2: np.ndarray, at: np.ndarray, pair: PairOptions) -> bool:
    degrees, mm = pose_difference(T1, T2, at)
    return degrees > pair.distinct_deg or mm > pair.distinct_mm


def _ransac(source: ScanFeatures, target: ScanFeatures, options: PairOptions) -> tuple[np.ndarray, np.ndarray, int]:
    """Hypotheses ``T_target_source`` (h, 4, 4) best supported first, each re-fitted on the
    matches it explains, their support (h,), and the number of feature matches."""
    _, fwd = cKDTree(target.fpfh).query(source.fpfh, k=1, workers=1)
    _, back = cKDTree(source.fpfh).query(target.fpfh, k=1, workers=1)
    if options.mutual_only:
        src = np.flatnonzero(back[fwd] == np.arange(len(fwd)))
        P, Q = source.keypoints_mm[src], target.keypoints_mm[fwd[src]]
    else:
        P = np.concatenate([source.keypoints_mm, source.keypoints_mm[back]])
        Q = np.concatenate([target.keypoints_mm[fwd], target.keypoints_mm])
    if len(P) < 3:
        return np.zeros((0, 4, 4)), np.zeros(0, np.int64), len(P)
    pick = np.random.default_rng(options.seed).integers(0, len(P), size=(options.draws, 3))
    edges_p = np.linalg.norm(P[pick] - P[np.roll(pick, 1, axis=1)], axis=2)
    edges_q = np.linalg.norm(Q[pick] - Q[np.roll(pick, 1, axis=1)], axis=2)
    ok = (np.minimum(edges_p, edges_q) >= 0.9 * np.maximum(edges_p, edges_q)).all(axis=1)
    ok &= (edges_p.min(axis=1) >= 2 * source.voxel_mm)  # no near-collinear clump of one voxel
    pick = pick[ok]
    hypotheses = _kabsch(P[pick], Q[pick])
    Pt, Qt, limit = np.ascontiguousarray(P.T), np.ascontiguousarray(Q.T), options.ransac_inlier_mm ** 2
    if len(hypotheses) == 0:
        return hypotheses, np.zeros(0, np.int64), len(P)
    support = np.concatenate([
        (((np.matmul(h[:, :3, :3], Pt) + h[:, :3, 3:] - Qt) ** 2).sum(axis=1) <= limit).sum(axis=1)
        for h in np.array_split(hypotheses, max(1, len(hypotheses) // 256))])
    order = np.argsort(-support, kind="stable")
    refit = []
    for T in hypotheses[order[: 50 * options.top_k]]:
        inl = np.linalg.norm(apply(T, P) - Q, axis=1) <= options.ransac_inlier_mm
        refit.append(_kabsch(P[inl][None], Q[inl][None])[0] if inl.sum() >= 3 else T)
    return np.array(refit), support[order[: len(refit)]], len(P)


def _overlap(a: SurfaceSample, b: SurfaceSample, T_b_a: np.ndarray, inlier_mm: float) -> float:
    """Share of a's surface samples with a measured point of b within inlier_mm."""
    if len(a.points_mm) == 0 or b.tree is None:
        return 0.0
    dist, _ = b.tree.query(apply(T_b_a, a.points_mm), distance_upper_bound=inlier_mm, workers=1)
    return float(np.isfinite(dist).mean())


def _refine_pair(source: ScanFeatures, target: ScanFeatures, T0: np.ndarray, support: int, pair: PairOptions,
                 refine: RefineOptions) -> tuple[float, float, np.ndarray, int] | None:
    """ICP from ``T0``: (fitness, point-to-plane RMS, T_target_source, support), None when the
    two surfaces never come within the gates."""
    try:
        result = refine_scan_poses([target.surface, source.surface], np.stack([np.eye(4), T0]), options=refine)
    except NothingToRefine:
        return None
    T = result.T_common_pass[1]
    counts = [result.pair_count.get(k, 0) for k in ((0, 1), (1, 0))]
    squares = sum(result.pair_rms_mm[k] ** 2 * c for k, c in zip(((0, 1), (1, 0)), counts) if c)
    rms = float(np.sqrt(squares / sum(counts))) if sum(counts) else np.inf
    fitness = max(_overlap(source.surface, target.surface, T, pair.inlier_mm),
                  _overlap(target.surface, source.surface, np.linalg.inv(T), pair.inlier_mm))
    return fitness, rms, T, support


def _probes(source: ScanFeatures, target: ScanFeatures, T: np.ndarray, pair: PairOptions) -> list[np.ndarray]:
    """Starts around pose ``T``: shifted ``1.5 distinct_mm`` both ways along the two long axes of
    the overlap, and turned ``1.5 distinct_deg`` both ways about its short axis (its normal, for
    a patch) through its centroid: where a surface can slide or turn on the other (a plate, a
    repeating pattern, a body of revolution), ICP from there stays away, and scores as well."""
    moved = apply(T, source.surface.points_mm)
    near = target.surface.tree.query(moved, distance_upper_bound=pair.inlier_mm, workers=1)[0] < np.inf
    if near.sum() < 10:
        return []
    patch = moved[near]
    centre = patch.mean(axis=0)
    axes = np.linalg.eigh(np.cov((patch - centre).T))[1][:, ::-1].T  # long, middle, short
    out = []
    for sign in (1.0, -1.0):
        for axis in axes[:2]:
            D = np.eye(4)
            D[:3, 3] = sign * 1.5 * pair.distinct_mm * axis
            out.append(D @ T)
        D = np.eye(4)
        D[:3, :3] = Rotation.from_rotvec(sign * np.radians(1.5 * pair.distinct_deg) * axes[2]).as_matrix()
        D[:3, 3] = centre - D[:3, :3] @ centre
        out.append(D @ T)
    return out


def register_pair(source: ScanFeatures, target: ScanFeatures, *, pair: PairOptions, refine: RefineOptions,
                  indices: tuple[int, int] = (0, 1)) -> PairRegistration:
    """``T_target_source`` of two scans with no initial pose, verified (see the module's notes).
    The runner-up is sought among the other RANSAC hypotheses and, where the best passes the
    overlap and RMS checks, from six starts around it (``_probes``). ``indices`` (source,
    target) only label the result."""
    centroid = (source.surface.points_mm if len(source.surface.points_mm) else source.keypoints_mm).mean(axis=0)
    hypotheses, support, matches = _ransac(source, target, pair)
    candidates: list[tuple[np.ndarray, int]] = []
    for T, s in zip(hypotheses, support):
        if all(_distinct(T, C, centroid, pair) for C, _ in candidates):
            candidates.append((T, int(s)))
        if len(candidates) == pair.top_k:
            break
    refined = [r for T0, s in candidates if (r := _refine_pair(source, target, T0, s, pair, refine)) is not None]
    label = dict(source=indices[0], target=indices[1], matches=matches)
    if not refined:
        return PairRegistration(**label, T_target_source=np.full((4, 4), np.nan), accepted=False,
                                reason=f"no hypothesis: {matches} feature matches, none refined to an overlap",
                                fitness=0.0, rms_mm=np.nan, runner_up_fitness=0.0, runner_up_rms_mm=np.nan,
                                runner_up_deg=np.nan, runner_up_mm=np.nan, ransac_support=0)

    # the best: the largest overlap among the poses whose RMS passes (any, when none does)
    def rank(r):
        return (r[1] > pair.max_rms_mm, -r[0], r[1])

    refined.sort(key=rank)
    fitness, rms, T, s = refined[0]
    if fitness >= pair.min_fitness and rms <= pair.max_rms_mm:
        refined += [r for T0 in _probes(source, target, T, pair)
                    if (r := _refine_pair(source, target, T0, 0, pair, refine)) is not None]
        refined.sort(key=rank)
        fitness, rms, T, s = refined[0]
    # the runner-up: the largest overlap among the other passing poses clearly apart from the best
    runner = next((r for r in refined[1:] if r[1] <= pair.max_rms_mm and _distinct(T, r[2], centroid, pair)),
                  None)
    r_fit, r_rms = (runner[0], runner[1]) if runner else (0.0, np.nan)
    r_deg, r_mm = pose_difference(T, runner[2], centroid) if runner else (np.nan, np.nan)
    problems = []
    if fitness < pair.min_fitness:
        problems.append(f"overlap {fitness:.3f} below {pair.min_fitness}")
    if rms > pair.max_rms_mm:
        problems.append(f"RMS {rms:.3f} mm above {pair.max_rms_mm} mm")
    if runner and r_fit >= pair.max_runner_up_ratio * fitness:
        problems.append(f"ambiguous: a pose {r_deg:.1f} deg / {r_mm:.1f} mm away has overlap {r_fit:.3f} "
                        f"(RMS {r_rms:.3f} mm) against {fitness:.3f} (RMS {rms:.3f} mm), ratio "
                        f"{r_fit / fitness:.2f} >= {pair.max_runner_up_ratio}")
    return PairRegistration(**label, T_target_source=T, accepted=not problems, reason="; ".join(problems),
                            fitness=fitness, rms_mm=rms, runner_up_fitness=r_fit, runner_up_rms_mm=r_rms,
                            runner_up_deg=r_deg, runner_up_mm=r_mm, ransac_support=s)


def register_scans(scans: list[ScanFeatures], *, pair: PairOptions, refine: RefineOptions,
                   fixed: int = 0) -> ScanRegistration:
    """Poses of all ``scans`` with none given: every pair registered (``register_pair``), a
    maximum spanning tree of the accepted pairs by overlap, poses chained from scan ``fixed``
    along it, then refined together (``refine_scan_poses``). Scans with no chain of accepted
    pairs to ``fixed`` are refused (NaN pose) and left out of the refinement."""
    n = len(scans)
    if n < 2 or not 0 <= fixed < n:
        raise ValueError(f"need 2 or more scans and fixed among them, got {n} scans, fixed {fixed}")
    pairs = tuple(register_pair(scans[s], scans[t], pair=pair, refine=refine, indices=(s, t))
                  for t in range(n) for s in range(t + 1, n))
    ok = [p for p in pairs if p.accepted]
    weight = coo_matrix(([2.0 - p.fitness for p in ok], ([p.target for p in ok], [p.source for p in ok])),
                        shape=(n, n)).tocsr()
    tree = minimum_spanning_tree(weight)
    tree = tree + tree.T
    order, parent = breadth_first_order(tree, fixed, directed=False, return_predecessors=True)
    by_pair = {(p.source, p.target): p.T_target_source for p in ok}
    T = np.full((n, 4, 4), np.nan)
    T[fixed] = np.eye(4)
    edges = []
    for k in order[1:]:
        p = parent[k]
        T_p_k = by_pair[(k, p)] if (k, p) in by_pair else np.linalg.inv(by_pair[(p, k)])
        T[k] = T[p] @ T_p_k
        edges.append((p, k))
    registered = np.zeros(n, bool)
    registered[order] = True
    result = None
    if len(order) > 1:  # refused scans take part as empty surfaces, so the result's indices are the scans'
        empty = SurfaceSample(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), view_direction=np.ones(3))
        result = refine_scan_poses([s.surface if registered[k] else empty for k, s in enumerate(scans)],
                                   np.where(registered[:, None, None], T, np.eye(4)), options=refine, fixed=fixed)
        T[registered] = result.T_common_pass[registered]
    method = tuple("reference" if k == fixed else "surfaces" if registered[k] else "refused" for k in range(n))

    def refused(k: int) -> str:  # its three pairs of largest overlap, with why each was refused
        mine = sorted((p for p in pairs if k in (p.source, p.target)), key=lambda p: -p.fitness)[:3]
        return "no chain of accepted pairs to the reference scan; best pairs: " + "; ".join(
            f"with scan {p.target if p.source == k else p.source}: {p.reason or 'accepted'}" for p in mine)

    reason = tuple("" if registered[k] else refused(k) for k in range(n))
    return ScanRegistration(T_world_scan=T, registered=registered, method=method, reason=reason, pairs=pairs,
                            tree=np.array(edges, np.int64).reshape(-1, 2), refine=result)
