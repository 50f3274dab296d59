"""The ``paper`` preset follows the paper's Table I: passes, lengths, durations, resolutions."""

from __future__ import annotations

import numpy as np
from numpy.testing import assert_allclose

from simulator.presets import preset_config
from simulator.robot import plan_passes


def test_paper_plan_matches_table_one():
    cfg = preset_config("paper")
    passes = plan_passes(cfg.plan, cfg.specimen, cfg.robot, z_top_mm=60.0,
                         standoff_mm=cfg.scanner.reference_distance_mm)
    along = [p for p in passes if p.direction == "along-length"]
    across = [p for p in passes if p.direction == "along-width"]
    assert (len(passes), len(along), len(across)) == (32, 24, 8)
    assert {p.length_mm for p in along} == {630.0}
    assert {p.length_mm for p in across} == {160.0}
    assert_allclose([p.duration_s for p in along], 42.0)
    assert_allclose([p.duration_s for p in across], 160 / 15, rtol=1e-9)  # ~11 s
    total_min = sum(p.duration_s for p in passes) / 60
    assert 17.5 < total_min < 18.5  # "~18 min of scanning"
    assert cfg.scanner.points_per_profile == 2048
    assert_allclose(cfg.scanner.x_spacing_mm, 0.02)
    assert_allclose(cfg.robot.profile_spacing_mm, 0.1)
    assert_allclose(cfg.robot.speed_mm_s, 15.0)
    assert_allclose(cfg.scanner.z_resolution_mm, 0.004)
    n_points = sum(p.n_profiles for p in passes) * cfg.scanner.points_per_profile
    assert n_points > 300e6  # hundreds of millions
    assert {p.setup for p in passes} == {"top", "bottom"}
    for p in passes:  # profiles 0.1 mm apart along the travel
        step = np.diff(p.nominal_sensor_poses(np.array([0.0, cfg.robot.profile_spacing_mm]))[:, :3, 3], axis=0)
        assert_allclose(np.linalg.norm(step), 0.1)
