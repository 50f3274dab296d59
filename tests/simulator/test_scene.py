"""The scene's sticker queries (simulator.scene.StickerSet) against the plain k-d tree search they
stand in for: the same nearest centre for every point, far or near, on the bound included."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from simulator.scene import StickerSet


@pytest.mark.parametrize("bound", [3.1, 0.05], ids=["sticker-reach", "coarsened-grid"])
def test_the_nearest_centre_is_the_k_d_trees(bound):
    rng = np.random.default_rng(5)
    centres = rng.uniform([-120, -30, -10], [120, 30, 10], (60, 3))
    stickers = StickerSet(centres=centres, normals=np.tile([0.0, 0.0, 1.0], (60, 1)), ids=np.arange(60),
                          faces=np.zeros(60, np.uint8), radius_mm=2.5, thickness_mm=0.1)
    on_bound = centres[rng.integers(0, 60, 300)] + bound * np.eye(3)[rng.integers(0, 3, 300)]
    near = centres[rng.integers(0, 60, 2000)] + rng.normal(0, bound / 2, (2000, 3))
    points = np.concatenate([rng.uniform([-150, -50, -20], [150, 50, 20], (20_000, 3)), near, on_bound,
                             [[np.nan, 0.0, 0.0]]])
    dist, idx = stickers._nearest_centre(points, bound)
    want_dist, want_idx = cKDTree(centres).query(points[:-1], k=1, distance_upper_bound=bound)
    assert np.isfinite(want_dist).sum() > 1000
    assert np.array_equal(dist[:-1], want_dist) and np.array_equal(idx[:-1], want_idx)
    assert dist[-1] == np.inf and idx[-1] == len(centres)  # a point that is not one is near nothing
