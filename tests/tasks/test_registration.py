"""Matching and the registration graph recover known transforms on synthetic targets."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.spatial.transform import Rotation

from schemas.reconstruction import RegistrationConfig
from tasks.graph import register_passes
from tasks.matching import AmbiguousMatch, kabsch, match_by_translation, match_rotation_invariant
from tasks.registration import RegistrationError, RegistrationGraph, solve_pass_poses

_CFG = RegistrationConfig()  # the pipeline's defaults
_SETTINGS = dict(min_common=_CFG.min_common_targets, max_offset_mm=_CFG.max_offset_mm, tolerance_mm=_CFG.tolerance_mm,
                 min_setup_targets=_CFG.min_setup_targets)


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


def _wall_and_decoy(rng, wall_height_mm: float):
    """Two setups of a part turned over by hand: setup A sees 20 stickers on its top, setup B 20 on
    its underside, and both see five on a side wall 12 mm high (nearly on a line when their height
    spread is small). Elsewhere three unrelated stickers, one in each set, form the same triangle: a
    decoy that a rigid motion fits exactly. Returns (a, b, T_a_b)."""
    T = _pose([180, 0, 4], [3, -5, 25])
    top = _stickers(rng, 20) + [0, 0, 6]
    bottom = _stickers(rng, 20) + [0, 0, -6]
    x = np.array([-120.0, -60.0, -5.0, 50.0, 110.0])
    wall = np.column_stack([x, np.full(5, 41.0), rng.uniform(-wall_height_mm / 2, wall_height_mm / 2, 5)])
    triangle = np.array([[0.0, 0.0, 0.0], [23.0, 0.0, 0.0], [7.0, 17.0, 0.0]])
    # far from the other stickers (a fixture's corner, say), so their distances are theirs alone
    decoy_a = _apply(_pose([0, 0, 30], [330, -30, 6]), triangle)
    decoy_b = _apply(_pose([0, 0, -70], [-330, 30, -6]), triangle)  # in B's own frame: no relation to A's
    noise = lambda n: rng.normal(0, 0.02, (n, 3))  # noqa: E731
    a = np.concatenate([top, wall, decoy_a]) + noise(28)
    b = np.concatenate([_apply(np.linalg.inv(T), np.concatenate([bottom, wall])), decoy_b]) + noise(28)
    return a, b, T


def test_stickers_nearly_on_a_line_and_a_decoy_triangle_are_refused_not_matched():
    """Issue 11, item 5: the only stickers both setups see lie nearly on a line, so no triple of
    them fixes the turn about it; the decoy triangle is the only exact fit. Before, the matcher
    returned the decoy (3 targets) and the run went on with the setups 180 deg apart; now the
    evidence is named."""
    a, b, _ = _wall_and_decoy(np.random.default_rng(7), wall_height_mm=0.5)
    with pytest.raises(AmbiguousMatch, match=r"brings only 3 targets together, expected 4 or more .*no evidence"):
        match_rotation_invariant(a, b, tolerance_mm=0.5)


def test_the_wall_stickers_are_matched_past_the_decoy_when_they_fix_the_turn():
    a, b, T = _wall_and_decoy(np.random.default_rng(7), wall_height_mm=10.0)
    m = match_rotation_invariant(a, b, tolerance_mm=0.5)
    assert {(i, j) for i, j in m.pairs} == {(20 + k, 20 + k) for k in range(5)}  # the wall, not the decoy
    assert_allclose(_apply(m.T_a_b, b[20:25]), a[20:25], atol=0.05)  # five stickers 10 mm high fix it there
    assert m.runner_up <= 3  # the decoy


def _two_setups_of(a, b, rng):
    """The wall-and-decoy scene as four passes: each setup's stickers split between two passes
    that share the middle ones, each pass shifted by a small robot error (within the setup's
    coarse alignment)."""
    targets, setups = [], []
    for name, stickers in (("top", a), ("bottom", b)):
        order = np.argsort(stickers[:, 0])
        for half in (order[: 2 * len(order) // 3], order[len(order) // 3:]):
            targets.append(stickers[np.sort(half)] + rng.normal(0, 0.2, 3))
            setups.append(name)
    return targets, setups


def test_the_run_refuses_near_collinear_shared_stickers_with_a_decoy_naming_the_evidence():
    """Issue 11 (Done when): the registration of a whole sample, not the matcher alone: two setups
    whose shared stickers lie nearly on a line, a decoy triangle elsewhere. It must refuse, naming
    the setups and the evidence, never return the decoy's transform."""
    a, b, _ = _wall_and_decoy(np.random.default_rng(7), wall_height_mm=0.5)
    targets, setups = _two_setups_of(a, b, np.random.default_rng(11))
    with pytest.raises(ValueError, match=r"setups top and bottom \(\d+ and \d+ targets\): .*no evidence"):
        register_passes(targets, setups, names=["t0", "t1", "b0", "b1"], **_SETTINGS)


def test_the_run_registers_the_wall_when_it_fixes_the_turn_past_the_decoy():
    a, b, T = _wall_and_decoy(np.random.default_rng(7), wall_height_mm=10.0)
    targets, setups = _two_setups_of(a, b, np.random.default_rng(11))
    reg = register_passes(targets, setups, names=["t0", "t1", "b0", "b1"], **_SETTINGS)
    pairs, runner_up = reg.setup_evidence["bottom"]
    assert pairs == 5 and runner_up <= 3  # the five wall stickers; the decoy at most the runner-up
    # the bottom setup's view of the wall lands where the top setup saw it (its passes' small
    # robot errors aside: 0.2 mm per axis)
    T_top_bottom = reg.T_first_setup["bottom"]
    assert_allclose(_apply(T_top_bottom, _apply(np.linalg.inv(T), a[20:25])), a[20:25], atol=0.5)
    assert reg.specimen_track.sum() == 10  # the wall's five tracks in each setup


def test_one_chance_sticker_deciding_the_turn_about_the_wall_is_refused():
    """The wall's five stickers lie within 0.5 mm of a line; turned about it, one of the top's 20
    stickers happens to land within the tolerance of one of the bottom's. Six targets agree, but
    the sixth alone decides the turn (here 11 deg off): refused, naming it."""
    a, b, _ = _wall_and_decoy(np.random.default_rng(15), wall_height_mm=0.5)
    with pytest.raises(AmbiguousMatch, match=r"brings 6 targets together, but without one of them \(at \[.*\] mm\) "
                                             r"the others lie nearly on a line \(spread 0\.\d\d mm off it"):
        match_rotation_invariant(a, b, tolerance_mm=0.5)


def test_walls_of_stickers_are_matched_right_or_refused_never_wrong():
    """Thirty draws of the wall-and-decoy scene per wall height. The match must never be wrong; at
    10 mm the wall's own stickers usually fix the turn and must be found. Measured: 15 of 30 right
    (before the candidates were ranked by how closely their distances agree: 8; the other 15
    refused, most with one wall sticker alone off the line); at 0.5 and 3 mm all refused."""
    right = {}
    for height in (0.5, 3.0, 10.0):
        right[height] = 0
        for seed in range(7, 37):
            a, b, T = _wall_and_decoy(np.random.default_rng(seed), wall_height_mm=height)
            try:
                m = match_rotation_invariant(a, b, tolerance_mm=0.5)
            except AmbiguousMatch:
                continue
            assert {(i, j) for i, j in m.pairs} == {(20 + k, 20 + k) for k in range(5)}, (height, seed)
            right[height] += 1
    assert right[10.0] >= 12, right


def test_two_transforms_with_the_same_support_are_refused_as_ambiguous():
    """Shared stickers symmetric under a half turn (a rectangle and its centre): the turned part and
    the part turned once more fit equally well; which setup is which cannot be told from them."""
    rng = np.random.default_rng(3)
    shared = np.array([[-60.0, -20, 0], [60, -20, 0], [60, 20, 0], [-60, 20, 0], [0, 0, 0]])
    T = _pose([180, 0, 0], [2, 3, 20])
    a = np.concatenate([_stickers(rng, 10) + [0, 0, 50], shared])
    b = _apply(np.linalg.inv(T), np.concatenate([shared, _stickers(rng, 10) - [0, 0, 50]]))
    with pytest.raises(AmbiguousMatch, match=r"ambiguous: the best rigid transform brings 5 targets together, a "
                                             r"clearly different one 5"):
        match_rotation_invariant(a + rng.normal(0, 0.02, a.shape), b + rng.normal(0, 0.02, b.shape), tolerance_mm=0.5)


def test_the_fixtures_stickers_staying_put_are_not_a_rival_to_the_turned_part():
    """Both setups see five stickers on the part's side wall, turned over with the part, and five
    on the fixture, which stays where it was (the identity between the setups' robot frames, within
    the coarse poses' error). The fixture's five alone make a transform as well supported as the
    part's: refused as ambiguous unless that transform is known to be the fixture's (``exclude``,
    which the pass registration sets to the identity); then the part's is taken and nothing near
    the identity counts as its rival."""
    rng = np.random.default_rng(7)
    T = _pose([180, 0, 4], [3, -5, 25])
    top, bottom = _stickers(rng, 20) + [0, 0, 6], _stickers(rng, 20) + [0, 0, -6]
    wall = np.column_stack([[-120.0, -60.0, -5.0, 50.0, 110.0], np.full(5, 41.0), rng.uniform(-5, 5, 5)])
    fixture = np.array([[-60.0, -70, -30], [-10, -75, -30], [40, -68, -30], [15, -110, -30], [-40, -105, -30]])
    noise = lambda n: rng.normal(0, 0.02, (n, 3))  # noqa: E731
    a = np.concatenate([top, wall, fixture]) + noise(30)
    b = np.concatenate([_apply(np.linalg.inv(T), np.concatenate([bottom, wall])), fixture + [0.4, -0.3, 0.2]]) + noise(30)
    with pytest.raises(AmbiguousMatch, match=r"brings 5 targets together, a clearly different one 5"):
        match_rotation_invariant(a, b, tolerance_mm=0.5)
    m = match_rotation_invariant(a, b, tolerance_mm=0.5, exclude=np.eye(4), exclude_within=(5.0, 3.0))
    assert {(i, j) for i, j in m.pairs} == {(20 + k, 20 + k) for k in range(5)}  # the wall, not the fixture
    assert_allclose(_apply(m.T_a_b, b[20:25]), a[20:25], atol=0.05)
    assert m.runner_up < 5
