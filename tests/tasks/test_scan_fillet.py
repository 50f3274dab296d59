"""A fillet's root line and plates found in points (tasks.scan_fillet) on the simulator's drawn
T-joint: a stem welded on both sides (the base under it on both sides, two parallel stem faces)
gives the corner of one stem face, ``out`` away from the stem there, and its sections measure
the drawn legs; two plates too close to parallel are no corner."""

from __future__ import annotations

import numpy as np
import pytest

from flows.stages.weld import section_settings
from schemas.reconstruction import WeldGeometryConfig
from schemas.simulation import TJointConfig
from simulator.tjoint import constant_fillet, fillet_profile, fillet_truth
from tasks.fillet_section import measure_fillet_line
from tasks.scan_fillet import find_fillet_root

TJ = TJointConfig()
FILLET = constant_fillet(leg_base=7.5, leg_stem=6.5, convexity=0.6, toe_radius_base=0.8, toe_radius_stem=0.5)
SETTINGS = WeldGeometryConfig()


def _sweep(ab: np.ndarray, *, length_mm: float = 30.0, seed: int = 0) -> np.ndarray:
    """Section points (a, b) swept along y every 0.5 mm: x = a, z = b; 10 um of noise."""
    ys = np.arange(0.0, length_mm + 1e-9, 0.5)
    points = np.concatenate([np.stack([ab[:, 0], np.full(len(ab), y), ab[:, 1]], 1) for y in ys])
    return points + np.random.default_rng(seed).normal(0.0, 0.01, points.shape)


def test_a_stem_welded_on_both_sides_gives_one_faces_corner_and_its_weld():
    ab = fillet_profile(TJ, FILLET, 0.0, 0.1)
    ab = ab[(ab[:, 0] <= 25.0) & (ab[:, 1] <= 25.0)]
    thick = TJ.stem_thickness_mm
    both = np.concatenate([ab, np.stack([-thick - ab[:, 0], ab[:, 1]], 1)])  # the other weld, mirrored
    root = find_fillet_root(_sweep(both))
    assert root.found == "auto" and abs(root.plates_angle_deg - 90.0) < 0.2
    corner_a = root.start_mm[0]
    assert min(abs(corner_a), abs(corner_a + thick)) < 0.05 and abs(root.start_mm[2]) < 0.05
    away = 1.0 if abs(corner_a) < 0.05 else -1.0  # out of the stem at that face
    assert np.allclose(root.out, (away, 0.0, 0.0), atol=2e-3) and np.allclose(root.up, (0.0, 0.0, 1.0), atol=2e-3)
    assert abs(abs(root.end_mm[1] - root.start_mm[1]) - 30.0) < 0.1  # the line runs where the points reach
    line = measure_fillet_line(_sweep(both), np.array([root.start_mm, root.end_mm]), np.asarray(root.out),
                               np.asarray(root.up), name="w", step_mm=5.0, section_half_width_mm=0.5, reach_mm=32.0,
                               end_margin_mm=2.0, settings=section_settings(SETTINGS), treated=False)
    truth = fillet_truth(TJ, FILLET, 0.0, "x")
    assert [p for p, _ in line.sections] == [5.0, 10.0, 15.0, 20.0, 25.0]  # 2 mm in from each end, every 5 mm
    for _, sec in line.sections:  # a leg under a rounding under 0.8 mm: within 0.1 mm (test_fillet_section.py)
        assert abs(sec.leg_base.value - truth.leg_base_mm) < 0.1 and abs(sec.leg_stem.value - truth.leg_stem_mm) < 0.1


def test_plates_nearly_parallel_are_no_corner():
    a = np.arange(0.0, 40.0, 0.1)
    bent = np.concatenate([np.stack([a, np.zeros_like(a)], 1), np.stack([40 + a, a * np.tan(np.radians(20))], 1)])
    with pytest.raises(ValueError, match=r"no stem: the points off the largest plane make no second plate at an angle "
                                         r"to it \(\d+ points on the next plane, 20\.0 deg to the first"):
        find_fillet_root(_sweep(bent))
    with pytest.raises(ValueError, match=r"points must be a finite \(n >= 100, 3\) array"):
        find_fillet_root(np.zeros((50, 3)))
