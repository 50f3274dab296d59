"""Each target centre's expected error from its rim fit (``tasks.target_weights``)."""

from __future__ import annotations

import numpy as np
import pytest

from tasks.target_weights import centre_sigmas, height_spread


def test_the_height_spread_is_the_robust_one_less_what_the_fits_explain():
    """Known answers: five heights 0.07-0.13 mm and one wild fit (0.3) whose own sigmas are 0.01:
    the spread is 1.4826 x the median absolute deviation about their median (0.115), and the
    scatter the fits leave unexplained sqrt(spread^2 - 0.01^2)."""
    h = np.array([0.07, 0.07, 0.1, 0.13, 0.13, 0.3])
    s = height_spread(h, np.full(6, 0.01))
    assert s.median_mm == pytest.approx(0.115)  # six heights: the mean of the middle two
    spread = 1.4826 * np.median(np.abs(h - 0.115))
    assert s.spread_mm == pytest.approx(spread)
    assert s.own_sigma_mm == pytest.approx(0.01)
    assert s.scatter_mm == pytest.approx(np.sqrt(spread**2 - 0.01**2))
    # fits whose own sigmas explain the spread leave no scatter
    assert height_spread(h, np.full(6, 0.2)).scatter_mm == 0.0


@pytest.mark.parametrize("heights, sigmas", [(np.zeros(3), np.zeros(2)), (np.zeros(0), np.zeros(0)),
                                             (np.zeros((2, 2)), np.zeros((2, 2)))])
def test_the_height_spread_refuses_what_is_not_one_sample(heights, sigmas):
    with pytest.raises(ValueError, match="two equal, non-empty"):
        height_spread(heights, sigmas)


def test_only_heights_past_the_gate_add_their_centres_move():
    """Four fits about a median of 0.1 mm with no unexplained scatter: the two within
    ``gate`` x their own sigma keep max(factor x RMS, floor); the two past it get
    ``height_factor`` x their centre's move per mm x their height's distance from the median."""
    h = np.array([0.1, 0.12, 0.1, 0.3])
    own = np.array([0.02, 0.02, 0.02, 0.02])
    spread = height_spread(np.array([0.08, 0.1, 0.1, 0.12]), np.full(4, 0.05))  # median 0.1, no scatter
    assert spread.scatter_mm == 0.0
    rms = np.array([0.02, 0.001, 0.02, 0.02])
    per = np.array([0.5, 0.5, 0.5, 0.4])
    kw = dict(rim_factor=0.8, floor_mm=0.002, height_factor=4.0, max_spread_ratio=2.0)
    sigma, gated = centre_sigmas(rms, h, own, per, spread, gate=2.0, **kw)
    assert gated.tolist() == [False, False, False, True]
    np.testing.assert_allclose(sigma, [0.016, 0.002, 0.016, 0.016 + 4.0 * 0.4 * 0.2])
    # a wider gate lets the 0.2 mm fit through; none: the rim's term alone
    assert not centre_sigmas(rms, h, own, per, spread, gate=11.0, **kw)[1].any()
    bare, none = centre_sigmas(rms, h, own, per, None, gate=None, **kw)
    np.testing.assert_allclose(bare, [0.016, 0.002, 0.016, 0.016])
    assert not none.any()


def test_the_heights_unexplained_scatter_widens_the_gate():
    """Fits whose own sigmas (0.038 mm) explain most of the heights' spread (0.048: the demo's) leave
    a scatter of 0.029 mm: a precise fit (own sigma 2 um) 40 um off the median is within two of
    its expected spread and keeps its sigma, where its own sigma alone would have gated it."""
    rng = np.random.default_rng(0)
    heights = 0.1 + 0.048 * rng.standard_normal(2000)
    spread = height_spread(heights, np.full(2000, 0.038))
    assert spread.consistent(2.0) and 0.025 < spread.scatter_mm < 0.035
    h = np.array([spread.median_mm + 0.04])
    kw = dict(rim_factor=0.8, floor_mm=0.002, gate=2.0, height_factor=4.0, max_spread_ratio=2.0)
    assert not centre_sigmas(np.array([0.01]), h, np.array([0.002]), np.array([0.3]), spread, **kw)[1].any()
    alone = height_spread(heights, np.full(2000, 0.06))  # own sigmas that explain it all: no scatter
    assert alone.scatter_mm == 0.0
    assert centre_sigmas(np.array([0.01]), h, np.array([0.002]), np.array([0.3]), alone, **kw)[1].all()


def test_heights_that_scatter_past_what_their_fits_allow_are_not_gated_on():
    """Precise fits (own sigma 6 um) whose heights spread 21 um (the paper preset's full
    resolution: 3.2 x): they do not measure one edge, and even a fit 0.2 mm off keeps its sigma."""
    rng = np.random.default_rng(1)
    spread = height_spread(0.024 + 0.021 * rng.standard_normal(400), np.full(400, 0.006))
    assert not spread.consistent(2.0) and spread.consistent(5.0)
    sigma, gated = centre_sigmas(np.array([0.01]), np.array([spread.median_mm + 0.2]), np.array([0.006]),
                                 np.array([0.3]), spread, rim_factor=0.8, floor_mm=0.002, gate=2.0,
                                 height_factor=4.0, max_spread_ratio=2.0)
    assert not gated.any() and sigma[0] == pytest.approx(0.008)


def test_a_gate_needs_the_samples_heights():
    with pytest.raises(ValueError, match="needs the sample's height spread"):
        centre_sigmas(np.ones(2), np.ones(2), np.ones(2), np.ones(2), None, rim_factor=0.8, floor_mm=0.002,
                      gate=2.0, height_factor=4.0, max_spread_ratio=2.0)
