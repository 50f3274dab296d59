"""A positioner's turn: the screw axis of a rigid turn (known answers), and the match of two
setups' targets on a prior turn (tasks.matching.match_with_prior)."""

from __future__ import annotations

import numpy as np
import pytest

from tasks.frames import screw_axis, turn_about_axis
from tasks.matching import AmbiguousMatch, match_with_prior, pose_difference


@pytest.mark.parametrize("point, direction, angle", [((3.0, 5.0, 40.0), (1.0, 0.01, 0.0), 180.0),
                                                     ((0.0, -20.0, 7.0), (0.2, 1.0, 0.1), 37.0),
                                                     ((10.0, 0.0, 0.0), (0.0, 0.0, 1.0), -90.0)])
def test_a_turn_about_an_axis_is_its_screw_axis_again(point, direction, angle):
    T = turn_about_axis(point, direction, angle)
    c, d, a, slide = screw_axis(T)
    u = np.asarray(direction) / np.linalg.norm(direction)
    assert abs(abs(d @ u) - 1) < 1e-12 and abs(slide) < 1e-9
    assert a == pytest.approx(abs(angle) if d @ u * np.sign(angle) > 0 else 360 - abs(angle), abs=1e-9)
    assert np.linalg.norm(np.cross(c - np.asarray(point), u)) < 1e-9  # the point lies on the axis
    # a known answer: a half turn about the x axis through (0, 0, 35) takes (10, 4, 40) to (10, -4, 30)
    half = turn_about_axis((0.0, 0.0, 35.0), (1.0, 0.0, 0.0), 180.0)
    assert np.allclose(half[:3, :3] @ [10.0, 4.0, 40.0] + half[:3, 3], [10.0, -4.0, 30.0])


def test_the_identity_has_no_axis():
    with pytest.raises(ValueError, match="no turn"):
        screw_axis(np.eye(4))


def _targets(rng, n=12):
    return np.c_[rng.uniform(-100, 100, n), rng.uniform(-25, 25, n), rng.uniform(30, 40, n)]


def test_targets_are_matched_where_the_prior_turn_puts_them():
    rng = np.random.default_rng(3)
    a = _targets(rng)
    T_true = turn_about_axis((0.0, 0.1, 35.0), (1.0, 0.0002, 0.0), 180.01)  # the part from setup a to b
    b = a @ T_true[:3, :3].T + T_true[:3, 3] + rng.normal(0, 0.01, a.shape)
    order = rng.permutation(len(b))
    b = b[order]
    prior = np.linalg.inv(turn_about_axis((0.0, 0.0, 35.6), (1.0, 0.0, 0.0), 180.0))  # calibrated 0.6 mm off
    m = match_with_prior(a, b, prior, tolerance_mm=2.0)
    assert len(m.pairs) == len(a) and np.all(order[m.pairs[:, 1]] == m.pairs[:, 0])
    deg, mm = pose_difference(m.T_a_b, np.linalg.inv(T_true), b)
    assert deg < 0.03 and mm < 0.03 and m.rms_mm < 0.03 and m.runner_up == 0  # targets 10 um apart from exact


def test_a_prior_turn_off_by_more_than_its_tolerance_or_targets_on_a_line_are_refused():
    rng = np.random.default_rng(4)
    a = _targets(rng)
    T = turn_about_axis((0.0, 0.0, 35.0), (1.0, 0.0, 0.0), 180.0)
    b = a @ T[:3, :3].T + T[:3, 3]
    wrong = np.linalg.inv(turn_about_axis((0.0, 0.0, 55.0), (1.0, 0.0, 0.0), 180.0))  # 20 mm off
    with pytest.raises(AmbiguousMatch, match=r"0 targets lie within 2 mm of where the prior turn puts them"):
        match_with_prior(a, b, wrong, tolerance_mm=2.0)
    line = np.c_[np.linspace(-50, 50, 6), np.zeros(6), np.full(6, 35.0)]
    with pytest.raises(AmbiguousMatch, match="lie on a line"):
        match_with_prior(line, line @ T[:3, :3].T + T[:3, 3], np.linalg.inv(T), tolerance_mm=2.0)
