"""Ingest: profiles and poses to world points."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from tasks.ingest import profile_points


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
