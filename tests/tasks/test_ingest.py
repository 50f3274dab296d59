"""Ingest: profiles and poses to world points."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from schemas.manifest import NominalMotion
from tasks.ingest import profile_points, sensor_poses


def test_known_pose_is_applied():
    T = np.repeat(np.eye(4)[None], 2, 0)
    T[1, :3, 3] = [0.0, 5.0, 0.0]
    T[:, :3, :3] = np.diag([1.0, -1.0, -1.0])  # looking down
    x = np.array([[1.0, np.nan], [2.0, 3.0]])
    z = np.array([[100.0, np.nan], [100.0, 50.0]])
    p = profile_points(x, z, T)
    assert_allclose(p[0, 0], [1.0, 0.0, -100.0])
    assert_allclose(p[1, 1], [3.0, 5.0, -50.0])
    assert np.isnan(p[0, 1]).all()


def test_bad_shapes_and_poses():
    with pytest.raises(ValueError, match="equal"):
        profile_points(np.zeros((2, 3)), np.zeros((2, 4)), np.repeat(np.eye(4)[None], 2, 0))
    with pytest.raises(ValueError, match=r"shape \(2, 4, 4\)"):
        profile_points(np.zeros((2, 3)), np.zeros((2, 3)), np.eye(4))
    T = np.repeat(np.eye(4)[None], 2, 0)
    T[0, 0, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        profile_points(np.zeros((2, 3)), np.zeros((2, 3)), T)


def _motion(**changes) -> NominalMotion:
    start = np.eye(4)
    start[:3, 3] = [10.0, -5.0, 200.0]
    fields = dict(T_world_flange_start=start.tolist(), direction_world=(0.0, 1.0, 0.0), speed_mm_s=15.0,
                  profile_rate_hz=150.0, length_mm=30.0)
    return NominalMotion(**(fields | changes))


def test_nominal_sweep_moves_the_start_pose_along_the_direction():
    T_flange_sensor = np.eye(4)
    T_flange_sensor[:3, 3] = [0.0, 0.0, 50.0]
    t = np.array([0.0, 0.5, 2.0])
    T = sensor_poses(T_flange_sensor, timestamp_s=t, T_world_flange=None, motion=_motion())
    assert_allclose(T[:, :3, 3], [[10.0, -5.0, 250.0], [10.0, 2.5, 250.0], [10.0, 25.0, 250.0]])
    assert_allclose(T[:, :3, :3], np.repeat(np.eye(3)[None], 3, 0))


def test_a_logged_pose_wins_over_the_nominal_sweep():
    logged = np.repeat(np.eye(4)[None], 2, 0)
    logged[:, 0, 3] = [1.0, 2.0]
    T = sensor_poses(np.eye(4), timestamp_s=np.array([0.0, 1.0]), T_world_flange=logged, motion=_motion())
    assert_allclose(T, logged)


def test_nominal_poses_of_a_sample_without_a_pose_log_follow_the_true_motion(no_pose_log_sample):
    """The simulated cell with ``log_profile_poses: false``: the nominal sweep differs from the
    true sensor poses only by the robot's per-pass rigid error and its speed ripple."""
    from data_catalog.manifests import load_manifest
    from data_catalog.passes import read_pass
    from data_catalog.truth import read_truth_pass

    sample = no_pose_log_sample
    manifest = load_manifest(sample)
    for _, entry in manifest.passes()[:3]:
        data = read_pass(sample / entry.file)
        assert data.T_world_flange is None and not entry.has_profile_poses
        T = sensor_poses(manifest.scanner.T_flange_sensor, timestamp_s=data.timestamp_s, T_world_flange=None,
                         motion=entry.nominal_motion)
        true = read_truth_pass(sample / "truth" / "passes" / f"{entry.pass_id}.zarr").T_world_sensor
        offset = np.linalg.norm(T[:, :3, 3] - true[:, :3, 3], axis=1)
        # a rigid error of sigma 0.25 mm, 0.02 deg at ~250 mm reach, plus a 1 % speed ripple (~12 um)
        assert offset.max() < 2.0
        assert offset.max() - offset.min() < 0.1  # nearly constant along the pass: the rigid part
