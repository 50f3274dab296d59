"""Matching and the registration graph recover known transforms on synthetic targets."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.spatial.transform import Rotation

from schemas.reconstruction import RegistrationConfig
from tasks.graph import register_passes
from tasks.matching import kabsch, match_by_translation, match_rotation_invariant
from tasks.registration import RegistrationError, RegistrationGraph, solve_pass_poses

_CFG = RegistrationConfig()  # the pipeline's defaults
_SETTINGS = dict(min_common=_CFG.min_common_targets, max_offset_mm=_CFG.max_offset_mm, tolerance_mm=_CFG.tolerance_mm)


def _pose(rotvec_deg, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    T[:3, 3] = t
    return T


def _apply(T, p):
    return p @ T[:3, :3].T + T[:3, 3]


def _stickers(rng, n=60):
    """Stickers on a 300 x 80 plate, at least 10 mm apart."""
    pts = []
    while len(pts) < n:
        c = np.array([rng.uniform(-150, 150), rng.uniform(-40, 40), rng.uniform(-0.5, 0.5)])
        if all(np.linalg.norm(c - p) > 10 for p in pts):
            pts.append(c)
    return np.array(pts)


def test_kabsch_recovers_a_known_transform():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 3)) * 50
    T = _pose([3, -2, 10], [5, -7, 2])
    assert_allclose(kabsch(src, _apply(T, src)), T, atol=1e-9)
    with pytest.raises(ValueError, match="n >= 3"):
        kabsch(src[:2], src[:2])


def test_translation_matching_pairs_the_shared_stickers():
    rng = np.random.default_rng(1)
    world = _stickers(rng)
    a_ids, b_ids = np.arange(0, 40), np.arange(25, 60)  # 15 shared
    shift = np.array([0.4, -0.3, 0.1])
    a = world[a_ids] + rng.normal(0, 0.02, (40, 3))
    b = world[b_ids] + shift + rng.normal(0, 0.02, (35, 3))
    m = match_by_translation(a, b)
    assert {(a_ids[i], b_ids[j]) for i, j in m.pairs} == {(k, k) for k in range(25, 40)}
    assert_allclose(m.translation_mm, shift, atol=0.02)


def test_rotation_invariant_matching_finds_the_turned_setup():
    rng = np.random.default_rng(2)
    world = _stickers(rng)
    T = _pose([180, 0, 3], [4, -6, 30])  # turned over by hand
    a = world[:45] + rng.normal(0, 0.02, (45, 3))
    b = _apply(np.linalg.inv(T), world[30:]) + rng.normal(0, 0.02, (30, 3))
    m = match_rotation_invariant(a, b)
    assert {(i, j + 30) for i, j in m.pairs} == {(k, k) for k in range(30, 45)}
    assert_allclose(m.T_a_b, T, atol=0.05)
    assert m.rms_mm < 0.05


def test_graph_solve_recovers_pass_errors_and_names_lost_passes():
    rng = np.random.default_rng(3)
    world = _stickers(rng, 80)
    windows = [(-150, -30), (-80, 40), (-10, 110), (60, 150)]
    truth = [np.eye(4)] + [_pose(rng.normal(0, 0.05, 3), rng.normal(0, 0.3, 3)) for _ in windows[1:]]
    targets = []
    for (lo, hi), E in zip(windows, truth):
        seen = world[(world[:, 0] > lo) & (world[:, 0] < hi)]
        targets.append(_apply(np.linalg.inv(E), seen) + rng.normal(0, 0.01, seen.shape))
    reg = register_passes(targets, ["top"] * 4, names=["p0", "p1", "p2", "p3"], **_SETTINGS)
    # the registered model is defined up to one rigid transform G (the gauge): fit it, then every
    # pass must agree with the truth over the surface it saw
    probes = [np.array([[x, y, 0.0] for x in np.linspace(lo, hi, 5) for y in (-40, 40)]) for lo, hi in windows]
    mapped = [_apply(T, _apply(np.linalg.inv(E), p)) for T, E, p in zip(reg.T_common_pass, truth, probes)]
    G = kabsch(np.concatenate(probes), np.concatenate(mapped))
    for p, q in zip(probes, mapped):
        assert np.linalg.norm(q - _apply(G, p), axis=1).max() < 0.03
    assert np.median(reg.result.residual_mm) < 0.03

    lonely = targets + [np.array([[500.0, 0, 0], [520.0, 5, 0], [540.0, -5, 0]])]
    with pytest.raises(RegistrationError, match=r"passes \['p4'\] share no chain"):
        register_passes(lonely, ["top"] * 5, names=["p0", "p1", "p2", "p3", "p4"], **_SETTINGS)


def test_graph_checks_its_shapes():
    with pytest.raises(ValueError, match="must agree"):
        RegistrationGraph(2, np.zeros((1, 2), int), np.zeros((2, 3)), np.zeros((1, 3)), np.repeat(np.eye(4)[None], 2, 0))
    g = RegistrationGraph(2, np.zeros((0, 2), int), np.zeros((0, 3)), np.zeros((0, 3)), np.repeat(np.eye(4)[None], 2, 0))
    with pytest.raises(ValueError, match="out of range"):
        solve_pass_poses(g, fixed=5)
