"""Matching sticker targets between passes.

Within a setup the robot's nominal poses align passes to a few tenths of a millimetre, and the
paper's two steps apply: (a) a target whose list of distances to the pass's other targets finds
no counterpart in the other pass is omitted; (b) the remaining candidates are paired by the
translation that most candidate pairs agree on. Between setups (turned by hand, no pose
relation) the same distance lists, being rotation invariant, propose correspondences, and the
rigid transform that the most of them agree on (RANSAC over triples, Kabsch) decides, on
evidence: three stickers whose distances agree fit *some* rigid motion whatever they are, so a
match needs ``min_inliers`` (4) targets brought together, and a clearly different transform that
brings nearly as many together makes the match ambiguous: refused, with both figures named,
never guessed (a part whose shared stickers lie nearly on a line, a decoy triangle elsewhere).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from tasks.frames import apply

__all__ = ["PairMatch", "match_by_translation", "RigidMatch", "AmbiguousMatch", "match_rotation_invariant", "kabsch",
           "match_with_prior",
           "pose_difference"]


@dataclass(frozen=True)
class PairMatch:
    """Index pairs (k, 2) into targets A and B, and the translation B - A they agree on (mm)."""

    pairs: np.ndarray
    translation_mm: np.ndarray
    n_omitted_a: int
    n_omitted_b: int


def kabsch(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares rigid transform (4, 4) mapping src (n, 3) onto dst (n, 3) (Arun 1987)."""
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"kabsch needs two (n >= 3, 3) arrays of equal shape, got {src.shape} and {dst.shape}")
    cs, cd = src.mean(0), dst.mean(0)
    U, _, Vt = np.linalg.svd((src - cs).T @ (dst - cd))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = cd - R @ cs
    return T


def _distance_signatures(points: np.ndarray, max_mm: float = np.inf) -> list[np.ndarray]:
    """Per point, the sorted distances to the other points (those up to ``max_mm``)."""
    d = np.linalg.norm(points[:, None] - points[None], axis=-1)
    out = []
    for i, row in enumerate(d):
        row = np.delete(row, i)
        out.append(np.sort(row[row <= max_mm]))
    return out


_MIN_SPREAD_MM = 2.0  # targets whose second singular value (about their centroid) is below this: a line


def _leave_one_out_spread(points: np.ndarray) -> tuple[int, float]:
    """(the target whose removal leaves the others nearest a line, their spread off it then): the
    second singular value of the others about their centroid, mm, the least over the targets."""
    spreads = [np.linalg.svd(np.delete(points, k, axis=0) - np.delete(points, k, axis=0).mean(0),
                             compute_uv=False)[1] for k in range(len(points))]
    k = int(np.argmin(spreads))
    return k, float(spreads[k])


def _distance_gaps(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """For each of the sorted distances a, how far the nearest of the sorted distances b is."""
    if a.size == 0 or b.size == 0:
        return np.full(a.size, np.inf)
    pos = np.clip(np.searchsorted(b, a), 1, b.size - 1) if b.size > 1 else np.zeros(a.size, int)
    return np.minimum(np.abs(b[pos] - a), np.abs(b[pos - 1] - a)) if b.size > 1 else np.abs(b[0] - a)


def _shared_distances(a: np.ndarray, b: np.ndarray, tol: float) -> int:
    """How many of the sorted distances a find a partner in the sorted distances b within tol."""
    return int(np.count_nonzero(_distance_gaps(a, b) <= tol))


def _agreement(a: np.ndarray, b: np.ndarray, tol: float) -> tuple[int, float]:
    """(how many of the sorted distances a find a partner in b within tol, how closely: the sum
    over those of exp(-(gap / (tol/5))**2 / 2)). Within a loose tolerance many distances agree by
    chance, evenly over the window; the true partner's agree to the centres' error: the closeness
    ranks it first where the count alone ties it with chance."""
    gaps = _distance_gaps(a, b)
    close = gaps[gaps <= tol]
    return len(close), float(np.exp(-0.5 * (close / (tol / 5)) ** 2).sum())


def match_by_translation(a_mm: np.ndarray, b_mm: np.ndarray, *, max_offset_mm: float = 3.0,
                         tolerance_mm: float = 0.3, min_shared: int = 2) -> PairMatch:
    """Pair targets of two coarsely aligned passes (n, 3) and (m, 3), mm, same frame."""
    a, b = np.asarray(a_mm, float).reshape(-1, 3), np.asarray(b_mm, float).reshape(-1, 3)
    sig_a, sig_b = _distance_signatures(a), _distance_signatures(b)
    keep_a = np.array([any(_shared_distances(s, t, tolerance_mm) >= min_shared for t in sig_b) for s in sig_a], bool)
    keep_b = np.array([any(_shared_distances(t, s, tolerance_mm) >= min_shared for s in sig_a) for t in sig_b], bool)
    ia, ib = np.flatnonzero(keep_a), np.flatnonzero(keep_b)
    empty = PairMatch(np.zeros((0, 2), int), np.zeros(3), int((~keep_a).sum()), int((~keep_b).sum()))
    if ia.size == 0 or ib.size == 0:
        return empty
    cand = [(i, j) for i in ia for j in cKDTree(b[ib]).query_ball_point(a[i], max_offset_mm)]
    cand = [(i, ib[j]) for i, j in cand]
    if not cand:
        return empty
    shifts = np.array([b[j] - a[i] for i, j in cand])
    votes = (np.linalg.norm(shifts[:, None] - shifts[None], axis=-1) <= tolerance_mm).sum(axis=1)
    best = shifts[votes == votes.max()].mean(axis=0)
    agree = np.linalg.norm(shifts - best, axis=1) <= tolerance_mm
    pairs, used_a, used_b = [], set(), set()
    for k in np.argsort(np.linalg.norm(shifts - best, axis=1)):
        i, j = cand[k]
        if agree[k] and i not in used_a and j not in used_b:
            pairs.append((i, j))
            used_a.add(i)
            used_b.add(j)
    pairs = np.array(sorted(pairs), int).reshape(-1, 2)
    translation = (b[pairs[:, 1]] - a[pairs[:, 0]]).mean(axis=0) if len(pairs) else np.zeros(3)
    return PairMatch(pairs, translation, int((~keep_a).sum()), int((~keep_b).sum()))


@dataclass(frozen=True)
class RigidMatch:
    """Index pairs (k, 2) into A and B and the transform T_a_b (4, 4) mapping B onto A;
    ``runner_up``: how many targets the best clearly different transform brought together (0: none
    was found), the evidence that this one is not a chance agreement."""

    pairs: np.ndarray
    T_a_b: np.ndarray
    rms_mm: float
    runner_up: int = 0


class AmbiguousMatch(ValueError):
    """The target sets do not decide one rigid transform: too few targets agree with the best, or a
    clearly different transform is nearly as well supported; the message gives the figures."""


def pose_difference(T1: np.ndarray, T2: np.ndarray, at: np.ndarray) -> tuple[float, float]:
    """How far apart two rigid transforms (4, 4) are: the angle of the rotation between them (deg),
    and the farthest they put any of the points ``at`` ((3,) or (k, 3), mm) apart (mm)."""
    cos = (np.trace(T1[:3, :3].T @ T2[:3, :3]) - 1.0) / 2.0
    moved = np.linalg.norm(np.reshape(at, (-1, 3)) @ (T1[:3, :3] - T2[:3, :3]).T + (T1[:3, 3] - T2[:3, 3]), axis=1)
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))), float(moved.max(initial=0.0))


def match_rotation_invariant(a_mm: np.ndarray, b_mm: np.ndarray, *, tolerance_mm: float = 0.2,
                             min_shared: int = 2, neighbourhood_mm: float = 120.0, per_target: int = 3,
                             iterations: int = 4000, seed: int = 0, min_inliers: int = 4,
                             max_runner_up_ratio: float = 0.75, distinct_deg: float = 2.0,
                             distinct_mm: float = 2.0, exclude: np.ndarray | None = None,
                             exclude_within: tuple[float, float] = (2.0, 2.0)) -> RigidMatch:
    """Match two target sets (n, 3), (m, 3) with no pose relation between them.

    Each target's distances to its neighbours (up to ``neighbourhood_mm``) are compared; every
    target keeps its ``per_target`` best-scoring partners as candidates; triples of candidates
    whose mutual distances agree in both sets propose rigid transforms (Kabsch), at most
    ``iterations`` of them, and the one most targets agree with wins, on two conditions, else
    AmbiguousMatch with the figures: it brings ``min_inliers`` or more targets together (any
    three with agreeing distances fit some rigid motion), and no transform differing from it by
    more than ``distinct_deg`` or ``distinct_mm`` (at the matched targets) brings together
    ``max_runner_up_ratio`` of its count or more (``RigidMatch.runner_up`` keeps that count).
    ``exclude`` (4, 4): a transform known to be another body's, with every transform within
    ``exclude_within`` (degrees, mm at its targets) of it neither taken nor a rival: between two
    setups, the identity (the fixture's stickers stay where they were while the part is turned).
    """
    a, b = np.asarray(a_mm, float).reshape(-1, 3), np.asarray(b_mm, float).reshape(-1, 3)
    sig_a, sig_b = _distance_signatures(a, neighbourhood_mm), _distance_signatures(b, neighbourhood_mm)
    agree = np.array([[_agreement(s, t, tolerance_mm) for t in sig_b] for s in sig_a]).reshape(len(a), len(b), 2)
    count, score = agree[..., 0], agree[..., 1]
    cand = []
    for i in range(len(a)):
        for j in np.argsort(-score[i], kind="stable")[:per_target]:
            if count[i, j] >= min_shared:
                cand.append((i, j))
    cand = np.array(cand, int).reshape(-1, 2)
    if len(cand) < 3:
        raise ValueError(f"fewer than 3 candidate correspondences between the target sets ({len(a)} and {len(b)} "
                         f"targets); they share too few stickers")
    # Guided sampling: a triple of candidate pairs is tried only when its distances agree in
    # both sets (distances are what a rigid motion keeps), best-scoring seeds first.
    order = np.argsort(-score[cand[:, 0], cand[:, 1]], kind="stable")
    cand = cand[order]
    ca, cb = a[cand[:, 0]], b[cand[:, 1]]
    tree_a = cKDTree(a)
    best_pairs = np.zeros((0, 2), int)
    hypotheses: list[tuple[int, np.ndarray]] = []  # (targets brought together, T) of every transform tried
    tries = 0
    for s1 in range(min(len(cand), 150)):
        d1 = np.abs(np.linalg.norm(ca - ca[s1], axis=1) - np.linalg.norm(cb - cb[s1], axis=1))
        span1 = np.linalg.norm(ca - ca[s1], axis=1)
        second = np.flatnonzero((d1 < tolerance_mm) & (span1 > 5) & (cand[:, 0] != cand[s1, 0])
                                & (cand[:, 1] != cand[s1, 1]))[:30]
        for s2 in second:
            d2 = np.abs(np.linalg.norm(ca - ca[s2], axis=1) - np.linalg.norm(cb - cb[s2], axis=1))
            third = np.flatnonzero((d1 < tolerance_mm) & (d2 < tolerance_mm) & (span1 > 5)
                                   & (np.linalg.norm(ca - ca[s2], axis=1) > 5))[:10]
            for s3 in third:
                trio = cand[[s1, s2, s3]]
                if len(set(trio[:, 0])) < 3 or len(set(trio[:, 1])) < 3:
                    continue
                src, dst = b[trio[:, 1]], a[trio[:, 0]]
                if np.linalg.svd(src - src.mean(0), compute_uv=False)[1] < _MIN_SPREAD_MM:
                    continue  # nearly collinear: the rotation about their line is unknown
                tries += 1
                T = kabsch(src, dst)
                dist, idx = tree_a.query(apply(T, b), distance_upper_bound=tolerance_mm)
                inl = np.flatnonzero(np.isfinite(dist))
                if exclude is not None:
                    degrees, mm = pose_difference(T, exclude, b[inl])
                    if degrees <= exclude_within[0] and mm <= exclude_within[1]:
                        continue
                hypotheses.append((len(inl), T))
                if len(inl) > len(best_pairs):
                    best_pairs = np.column_stack([idx[inl], inl])
                if tries >= iterations:
                    break
            if tries >= iterations:
                break
        if tries >= iterations:
            break
    if len(best_pairs) < 3:
        raise AmbiguousMatch("no rigid transform brings 3 targets of the two sets together")
    if len(best_pairs) < min_inliers:
        raise AmbiguousMatch(f"the best rigid transform brings only {len(best_pairs)} targets together, expected "
                             f"{min_inliers} or more (any 3 stickers whose distances agree fit some rigid motion: "
                             "no evidence)")
    T = kabsch(b[best_pairs[:, 1]], a[best_pairs[:, 0]])
    at = b[best_pairs[:, 1]]
    weakest, spread = _leave_one_out_spread(at)
    if spread < _MIN_SPREAD_MM:
        raise AmbiguousMatch(f"the best rigid transform brings {len(best_pairs)} targets together, but without one of "
                             f"them (at {np.round(a[best_pairs[weakest, 0]], 1).tolist()} mm) the others lie nearly on a "
                             f"line (spread {spread:.2f} mm off it, expected {_MIN_SPREAD_MM:g} or more): one sticker alone "
                             "would decide the turn about that line, which a chance coincidence can (no evidence)")

    def distinct(other: np.ndarray) -> bool:
        degrees, mm = pose_difference(T, other, at)
        return degrees > distinct_deg or mm > distinct_mm

    runner_up = max((count for count, other in hypotheses if distinct(other)), default=0)
    if runner_up >= max_runner_up_ratio * len(best_pairs):
        raise AmbiguousMatch(f"ambiguous: the best rigid transform brings {len(best_pairs)} targets together, a "
                             f"clearly different one {runner_up} (more than {distinct_deg:g} deg or {distinct_mm:g} mm "
                             f"apart; expected at most {max_runner_up_ratio:g} of the best's)")
    moved = apply(T, at)
    rms = float(np.sqrt(np.mean(np.sum((moved - a[best_pairs[:, 0]]) ** 2, axis=1))))
    return RigidMatch(pairs=best_pairs[np.argsort(best_pairs[:, 0])], T_a_b=T, rms_mm=rms, runner_up=runner_up)


def match_with_prior(a_mm: np.ndarray, b_mm: np.ndarray, T_a_b_prior: np.ndarray, *, tolerance_mm: float,
                     min_inliers: int = 3, min_spread_mm: float = 1.0) -> RigidMatch:
    """Match two target sets (n, 3), (m, 3) whose relation is known within ``tolerance_mm`` (a
    positioner's calibrated turn): each of B's targets moved by ``T_a_b_prior`` and A's nearest
    within the tolerance, both each other's nearest, is a pair; the rigid transform is fitted on
    the pairs, and the pairs taken again with it within a third of the tolerance. An
    ``AmbiguousMatch`` names the count when fewer than ``min_inliers`` pairs, or pairs all on
    one line (within ``min_spread_mm``), remain: the prior is then wrong by more than its tolerance,
    or the setups share too few targets."""
    from scipy.spatial import cKDTree

    a, b = np.asarray(a_mm, float).reshape(-1, 3), np.asarray(b_mm, float).reshape(-1, 3)
    if len(a) == 0 or len(b) == 0:
        raise AmbiguousMatch(f"no targets to match ({len(a)} and {len(b)})")
    tree_a = cKDTree(a)
    T = np.asarray(T_a_b_prior, float)
    pairs = np.zeros((0, 2), np.int64)
    for tolerance in (tolerance_mm, tolerance_mm / 3):
        moved = b @ T[:3, :3].T + T[:3, 3]
        d, nearest = tree_a.query(moved, distance_upper_bound=tolerance)
        found = np.flatnonzero(np.isfinite(d))
        back = cKDTree(moved).query(a[nearest[found]])[1]
        pairs = np.stack([nearest[found], found], axis=1)[back == found].astype(np.int64)
        if len(pairs) < min_inliers:
            break
        T = kabsch(b[pairs[:, 1]], a[pairs[:, 0]])
    if len(pairs) < min_inliers:
        raise AmbiguousMatch(f"{len(pairs)} targets lie within {tolerance_mm:g} mm of where the prior turn puts "
                             f"them (expected {min_inliers} or more)")
    centred = a[pairs[:, 0]] - a[pairs[:, 0]].mean(0)
    spread = np.linalg.svd(centred, compute_uv=False)[1] / np.sqrt(len(pairs)) if len(pairs) > 2 else 0.0
    if spread < min_spread_mm:
        raise AmbiguousMatch(f"the {len(pairs)} targets the prior turn brings together lie on a line "
                             f"(within {spread:.2f} mm; expected {min_spread_mm:g} mm or more off it)")
    rms = float(np.sqrt(np.mean(np.sum((b[pairs[:, 1]] @ T[:3, :3].T + T[:3, 3] - a[pairs[:, 0]]) ** 2, axis=1))))
    return RigidMatch(pairs=pairs[np.argsort(pairs[:, 0])], T_a_b=T, rms_mm=rms, runner_up=0)
