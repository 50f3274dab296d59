"""The IIW effective notch stress's geometry and S-N curve (``tasks.plate_section.rounded_notches``,
``drawn_profile``; ``tasks.fatigue.notch_cycles``): a notch rounded to the reference radius is
an arc of that radius tangent to both sides, nothing wider or convex moves, the drawn weld's caps
are the circular segments asked for, and the life is the curve's by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tasks.fatigue import notch_cycles
from tasks.plate_section import PlateProfile, drawn_profile, rounded_notches


def _profile(x: np.ndarray, top: np.ndarray, bottom: np.ndarray) -> PlateProfile:
    every = np.ones(len(x), bool)
    return PlateProfile(x_mm=x, top_mm=top, bottom_mm=bottom, measured_top=every, measured_bottom=every)


@pytest.mark.parametrize("flank_deg", [20.0, 30.0, 60.0])
def test_a_sharp_toe_becomes_an_arc_of_the_reference_radius_tangent_to_plate_and_flank(flank_deg):
    x = np.arange(-10.0, 10.0, 0.01)
    top = 5.0 + np.maximum(x, 0.0) * math.tan(math.radians(flank_deg))  # plate, then a flank rising at x = 0
    rounded = rounded_notches(_profile(x, top, np.full(len(x), -5.0)), 1.0)
    added = rounded.top_mm - top
    assert np.all(added >= -1e-12)  # material is only added
    moved = added > 1e-4  # (the bins next to the arc's ends move by less: the disk stands on the bins)
    # the arc's centre: one radius above the plate, on the bisector of the corner's angle; its ends
    # where a circle there touches the plate (x = centre) and the flank
    half = math.radians(flank_deg) / 2
    cx, cy = -math.tan(half), 6.0
    assert np.all(np.abs(np.hypot(x[moved] - cx, rounded.top_mm[moved] - cy) - 1.0) < 0.003)
    assert x[moved].min() == pytest.approx(cx, abs=0.02)
    assert x[moved].max() == pytest.approx(cx + math.sin(math.radians(flank_deg)), abs=0.02)
    assert np.array_equal(rounded.bottom_mm, np.full(len(x), -5.0))  # a flat face keeps its place


def test_a_notch_wider_than_the_radius_and_every_convex_shape_are_kept():
    x = np.arange(-10.0, 10.0, 0.01)
    # a groove of radius 2 mm, 3 mm wide at the plate (0.68 mm deep)
    groove = np.where(np.abs(x) < 1.5, math.sqrt(4.0 - 1.5 ** 2) - np.sqrt(np.maximum(4.0 - x ** 2, 0.0)), 0.0)
    cap = np.where(np.abs(x) < 4.0, np.sqrt(np.maximum(16.0 - x ** 2, 0.0)), 0.0)  # a convex cap
    rounded = rounded_notches(_profile(x, 5.0 + groove, -5.0 - cap), 1.0)
    inside = np.abs(x) < 1.2  # the groove's floor: the disk of 1 mm fits into a groove of 2 mm
    # (within 0.2 um: the disk's centre stands on the 0.01 mm bins, not between them)
    assert np.max(np.abs(rounded.top_mm - (5.0 + groove))[inside]) < 2e-4
    # the cap's crown is kept; only the corners where it meets the plate are filled (the two toes)
    crown = np.abs(x) < 3.0
    assert np.max(np.abs(rounded.bottom_mm - (-5.0 - cap))[crown]) < 2e-4
    assert np.all(rounded.bottom_mm <= -5.0 - cap + 1e-12) and np.any(rounded.bottom_mm < -5.0 - cap - 1e-3)


def test_the_drawn_caps_are_the_circular_segments_asked_for():
    drawn = drawn_profile(thickness_mm=20.0, caps={"top": (16.0, 2.0)}, half_length_mm=30.0, bin_mm=0.05)
    assert drawn.top_mm.max() == pytest.approx(12.0)
    assert np.all(drawn.bottom_mm == -10.0)  # no bottom cap asked for
    rises = drawn.x_mm[drawn.top_mm > 10.0 + 1e-9]
    assert rises.min() == pytest.approx(-8.0, abs=0.06) and rises.max() == pytest.approx(8.0, abs=0.06)
    with pytest.raises(ValueError, match="top cap"):
        drawn_profile(thickness_mm=20.0, caps={"top": (16.0, 0.0)}, half_length_mm=30.0, bin_mm=0.05)
    with pytest.raises(ValueError, match="radius_mm must be positive"):
        rounded_notches(drawn, 0.0)


def test_the_life_is_the_iiw_curve_by_hand():
    assert notch_cycles(225.0, 225.0, 3.0) == pytest.approx(2e6)
    assert notch_cycles(450.0, 225.0, 3.0) == pytest.approx(2.5e5)
    # beyond the knee at 1e7 cycles the slope is 22: the knee's range is 225 (2e6 / 1e7)^(1/3)
    knee = 225.0 * 0.2 ** (1 / 3)
    assert notch_cycles(knee, 225.0, 3.0) == pytest.approx(1e7)
    assert notch_cycles(knee / 1.1, 225.0, 3.0) == pytest.approx(1e7 * 1.1 ** 22)
    with pytest.raises(ValueError, match="must be positive"):
        notch_cycles(0.0, 225.0, 3.0)
