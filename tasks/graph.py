"""From per-pass target centres to registered pass poses: the registration graph stage.

Within each setup, pass pairs are matched by translation (the nominal robot poses are close);
each setup is solved on its own; the setups' consolidated targets are then matched without any
pose relation (the specimen was turned by hand), and all passes are solved together. Targets
seen in both setups lie on the specimen (fixture targets move relative to it between setups).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from tasks.matching import match_by_translation, match_rotation_invariant, match_with_prior, pose_difference
from tasks.registration import RegistrationError, RegistrationGraph, RegistrationResult, solve_pass_poses

__all__ = ["PairReport", "PassRegistration", "register_passes", "setup_turn"]

_FIXTURE_DEG = 5.0  # a setup's match this close to the identity is the fixture's (a turned part moves far more)


@dataclass(frozen=True)
class PairReport:
    pass_a: int
    pass_b: int
    n_common: int  # matched targets


@dataclass(frozen=True)
class PassRegistration:
    """``T_common_pass`` (n, 4, 4): maps each pass's (coarsely aligned) points into the common
    frame. ``tracks``: per physical target, its (pass, target index) observations.
    ``specimen_targets_mm`` (k, 3): consolidated targets seen in more than one setup."""

    T_common_pass: np.ndarray
    result: RegistrationResult
    graph: RegistrationGraph
    pairs: list[PairReport]
    weak_pairs: list[PairReport]  # overlapping passes with fewer than 3 common targets
    tracks: list[list[tuple[int, int]]]
    track_positions_mm: np.ndarray
    specimen_track: np.ndarray  # (tracks,) bool
    T_first_setup: dict[str, np.ndarray] = field(default_factory=dict)
    # per later setup, the evidence of its match to the first: (targets brought together, the most
    # a clearly different transform brought together)
    setup_evidence: dict[str, tuple[int, int]] = field(default_factory=dict)
    # per later setup matched on a prior turn (a positioner's): how far the stickers' own match lies
    # from it, (deg, mm at the matched targets)
    prior_difference: dict[str, tuple[float, float]] = field(default_factory=dict)


class _UnionFind:
    def __init__(self) -> None:
        self.parent: dict = {}

    def find(self, x):
        self.parent.setdefault(x, x)
        while self.parent[x] != x:
            self.parent[x] = self.parent[self.parent[x]]
            x = self.parent[x]
        return x

    def union(self, a, b) -> None:
        self.parent[self.find(a)] = self.find(b)


def _groups(members: list[int], matched) -> list[list[int]]:
    """Connected groups of passes among ``members`` by matched pairs."""
    uf = _UnionFind()
    for k in members:
        uf.find(k)
    for i, j, _ in matched:
        if i in uf.parent and j in uf.parent:
            uf.union(i, j)
    groups: dict = {}
    for k in members:
        groups.setdefault(uf.find(k), []).append(k)
    return list(groups.values())


def _edges(targets, idx_pairs):
    ep, pa, pb = [], [], []
    for i, j, pairs in idx_pairs:
        for a, b in pairs:
            ep.append((i, j))
            pa.append(targets[i][a])
            pb.append(targets[j][b])
    return (np.array(ep, int).reshape(-1, 2), np.array(pa, float).reshape(-1, 3), np.array(pb, float).reshape(-1, 3))


def register_passes(targets: list[np.ndarray], setups: list[str], *, names: list[str] | None = None,
                    min_common: int, max_offset_mm: float, tolerance_mm: float,
                    min_setup_targets: int, priors: dict[str, tuple[np.ndarray, float]] | None = None
                    ) -> PassRegistration:
    """targets: per pass (k_i, 3) target centres, mm, coarsely aligned within its setup;
    setups: per pass its setup name. The first pass is held fixed. A RegistrationError carries
    the pass pairs that matched fewer than ``min_common`` targets; a ValueError names a setup whose
    match to the first is not decided by ``min_setup_targets`` or more targets, or is ambiguous
    (tasks.matching.match_rotation_invariant). ``priors``: per later setup, (T_first_setup (4, 4):
    its coarse frame into the first setup's, as a positioner's calibrated turn gives it; the
    tolerance, mm): that setup is matched on the prior (tasks.matching.match_with_prior: three
    targets not in a line suffice) and its difference from the match is kept."""
    weak: list[PairReport] = []
    try:
        return _register(targets, setups, names, min_common, max_offset_mm, tolerance_mm, weak, min_setup_targets,
                         priors or {})
    except RegistrationError as exc:
        raise RegistrationError(str(exc), exc.unregistered, weak) from None


def setup_turn(setups: list[str], T_common_pass: np.ndarray, a: str, b: str) -> np.ndarray:
    """(4, 4): how the part moved from setup ``a`` to setup ``b`` in the cell (a point of the
    part at p in ``a``'s coarse frame lies at T p in ``b``'s), from the registered poses: per
    setup, its passes' maps from the common frame into the cell (each off by its own pose error)
    averaged, rotations and translations apart. (A rigid fit of the detections instead turns the
    passes' translation errors into rotation: each pass sees its own strip of the part.)"""
    from scipy.spatial.transform import Rotation

    means = {}
    for setup in (a, b):
        T = np.linalg.inv(np.asarray(T_common_pass, float)[[k for k, s in enumerate(setups) if s == setup]])
        mean = np.eye(4)
        mean[:3, :3] = Rotation.from_matrix(T[:, :3, :3]).mean().as_matrix()
        mean[:3, 3] = T[:, :3, 3].mean(axis=0)
        means[setup] = mean
    return means[b] @ np.linalg.inv(means[a])


def _register(targets, setups, names, min_common, max_offset_mm, tolerance_mm, weak,
              min_setup_targets, priors) -> PassRegistration:
    n = len(targets)
    if len(setups) != n:
        raise ValueError("targets and setups must have one entry per pass")
    names = names or [str(i) for i in range(n)]
    setup_names = list(dict.fromkeys(setups))
    matched, reports = [], []
    uf = _UnionFind()
    for i in range(n):
        for j in range(i + 1, n):
            if setups[i] != setups[j] or len(targets[i]) == 0 or len(targets[j]) == 0:
                continue
            m = match_by_translation(targets[i], targets[j], max_offset_mm=max_offset_mm, tolerance_mm=tolerance_mm)
            if len(m.pairs) >= min_common:
                matched.append((i, j, m.pairs))
                reports.append(PairReport(i, j, len(m.pairs)))
                for a, b in m.pairs:
                    uf.union((i, int(a)), (j, int(b)))
            elif len(m.pairs) > 0:
                weak.append(PairReport(i, j, len(m.pairs)))
    T_initial = np.repeat(np.eye(4)[None], n, axis=0)
    # 1. each setup on its own; a group of passes tied to the rest of its setup only through the
    #    other setup (e.g. side passes) is solved apart and keeps the robot's coarse pose for now
    for s in setup_names:
        for members in _groups([k for k in range(n) if setups[k] == s], matched):
            local = {k: q for q, k in enumerate(members)}
            sub = [(local[i], local[j], p) for i, j, p in matched if i in local and j in local]
            ep, pa, pb = _edges([targets[k] for k in members], sub)
            g = RegistrationGraph(len(members), ep, pa, pb, np.repeat(np.eye(4)[None], len(members), axis=0))
            T_initial[members] = solve_pass_poses(g, fixed=0, names=[names[k] for k in members]).T_common_initial
    # 2. consolidated targets per setup, then the setups to each other
    groups: dict = {}
    for p in range(n):  # every detection is a track, matched ones share theirs
        for t in range(len(targets[p])):
            groups.setdefault(uf.find((p, t)), set()).add((p, t))
    tracks = [sorted(v) for v in groups.values()]
    positions = np.array([np.mean([T_initial[p, :3, :3] @ targets[p][t] + T_initial[p, :3, 3] for p, t in tr], axis=0)
                          for tr in tracks]).reshape(-1, 3)
    track_setup = [setups[tr[0][0]] for tr in tracks]
    cross = []
    T_first_setup = {setup_names[0]: np.eye(4)}
    evidence: dict[str, tuple[int, int]] = {}
    prior_difference: dict[str, tuple[float, float]] = {}
    for s in setup_names[1:]:
        ta = [k for k, ts in enumerate(track_setup) if ts == setup_names[0]]
        tb = [k for k, ts in enumerate(track_setup) if ts == s]
        if s in priors:  # a positioner's turn: the targets where it puts them
            T_prior, prior_tolerance = priors[s]
            try:
                rm = match_with_prior(positions[ta], positions[tb], T_prior, tolerance_mm=prior_tolerance)
            except ValueError as exc:
                raise ValueError(f"setups {setup_names[0]} and {s} ({len(ta)} and {len(tb)} targets), matched on the "
                                 f"positioner's turn: {exc}; is the positioner's axis calibrated (the manifest's "
                                 "setups' positioner) and the part still clamped between the setups?") from None
            matched_b = positions[tb][rm.pairs[:, 1]]
            prior_difference[s] = pose_difference(rm.T_a_b, T_prior, matched_b)
        else:
            rm = None
        try:
            # the fixture's stickers stay where they were (the identity, within the coarse poses'
            # error) while the part is turned: their match is neither the part's nor its rival
            rm = rm or match_rotation_invariant(positions[ta], positions[tb], tolerance_mm=max(tolerance_mm, 0.5),
                                                min_shared=2, min_inliers=min_setup_targets, exclude=np.eye(4),
                                                exclude_within=(_FIXTURE_DEG, max_offset_mm))
        except ValueError as exc:
            raise ValueError(f"setups {setup_names[0]} and {s} ({len(ta)} and {len(tb)} targets): {exc}; the specimen "
                             f"must show {min_setup_targets} or more stickers, not on one line, to passes of both "
                             "setups (registration.min_setup_targets), and must have been moved between them "
                             f"(targets that stay within {_FIXTURE_DEG:g} deg and {max_offset_mm:g} mm are the "
                             "fixture's)") from None
        T_first_setup[s] = rm.T_a_b
        evidence[s] = (len(rm.pairs), rm.runner_up)
        for k in range(n):
            if setups[k] == s:
                T_initial[k] = rm.T_a_b @ T_initial[k]
        for a, b in rm.pairs:
            cross.append((tracks[ta[a]], tracks[tb[b]]))
    # 3. everything together, the cross-setup tracks tying the setups
    ep, pa, pb = _edges(targets, matched)
    xe, xa, xb = [], [], []
    specimen = np.zeros(len(tracks), bool)
    index = {tuple(tr): k for k, tr in enumerate(tracks)}
    for tr_a, tr_b in cross:
        specimen[index[tuple(tr_a)]] = specimen[index[tuple(tr_b)]] = True
        for p, t in tr_a:
            for q, u in tr_b:
                xe.append((p, q))
                xa.append(targets[p][t])
                xb.append(targets[q][u])
    if xe:
        ep = np.concatenate([ep, np.array(xe)])
        pa = np.concatenate([pa, np.array(xa)])
        pb = np.concatenate([pb, np.array(xb)])
    graph = RegistrationGraph(n, ep, pa, pb, T_initial)
    result = solve_pass_poses(graph, fixed=0, names=names)
    final = np.array([np.mean([result.T_common_initial[p, :3, :3] @ targets[p][t] + result.T_common_initial[p, :3, 3]
                               for p, t in tr], axis=0) for tr in tracks]).reshape(-1, 3)
    return PassRegistration(T_common_pass=result.T_common_initial, result=result, graph=graph, pairs=reports,
                            weak_pairs=weak, tracks=tracks, track_positions_mm=final, specimen_track=specimen,
                            T_first_setup=T_first_setup, setup_evidence=evidence, prior_difference=prior_difference)
