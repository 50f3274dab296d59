"""Statistical outlier removal on organized passes: recovers the simulator's outlier labels."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from data_catalog.manifests import load_manifest
from data_catalog.truth import read_truth_pass
from flows.stages.passes import load_pass_points
from schemas.reconstruction import DenoiseConfig
from schemas.truth import PointLabel
from tasks.denoise import remove_statistical_outliers


SETTINGS = DenoiseConfig()  # the pipeline's defaults


def _denoise(points, **changes):
    cfg = SETTINGS.model_copy(update=changes)
    return remove_statistical_outliers(points, k=cfg.k, alpha=cfg.alpha, window_rows=cfg.window_rows,
                                       window_cols=cfg.window_cols)


def _world_points(sample, manifest, entry):
    return load_pass_points(sample, manifest, entry)[2]


def test_recovers_true_outliers_on_the_ci_sample(ci_sample):
    manifest = load_manifest(ci_sample)
    found = total_out = lost = total_valid = 0
    for _, entry in manifest.passes()[:4]:
        points = _world_points(ci_sample, manifest, entry)
        labels = read_truth_pass(ci_sample / "truth" / "passes" / f"{entry.pass_id}.zarr").label
        result = _denoise(points)
        outlier = labels == PointLabel.OUTLIER
        valid = labels == PointLabel.VALID
        found += np.count_nonzero(outlier & ~result.keep)
        total_out += np.count_nonzero(outlier)
        lost += np.count_nonzero(valid & ~result.keep)
        total_valid += np.count_nonzero(valid)
    assert total_out > 500
    assert found / total_out > 0.95, found / total_out
    assert lost / total_valid < 0.05, lost / total_valid


def test_agrees_with_open3d_on_which_points_go(ci_sample):
    manifest = load_manifest(ci_sample)
    _, entry = manifest.passes()[0]
    points = _world_points(ci_sample, manifest, entry)
    result = _denoise(points)
    flat = points.reshape(-1, 3)
    valid = np.isfinite(flat).all(1)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(flat[valid]))
    _, kept = cloud.remove_statistical_outlier(nb_neighbors=SETTINGS.k, std_ratio=SETTINGS.alpha)
    peer = np.zeros(valid.sum(), bool)
    peer[kept] = True
    ours = result.keep.reshape(-1)[valid]
    assert np.mean(ours == peer) > 0.9


def test_a_lone_spike_goes_and_a_plane_stays():
    rows, cols = np.mgrid[0:40, 0:60]
    points = np.stack([cols * 0.1, rows * 0.1, np.zeros_like(rows, dtype=float)], -1).astype(float)
    points[:, :, 2] += np.random.default_rng(0).normal(0, 0.002, rows.shape)
    points[20, 30, 2] = 2.0
    points[5, 5] = np.nan
    result = _denoise(points, alpha=2.0)
    assert not result.keep[20, 30]
    assert not result.keep[5, 5]
    assert result.keep.sum() >= 40 * 60 - 2 - 40  # only the spike, the hole and few of their neighbours


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [({"k": 0}, "k must be at least 1"), ({"alpha": 0.0}, "alpha must be positive"),
     ({"k": 30, "window_rows": 1, "window_cols": 1}, "holds fewer than k = 30")],
)
def test_bad_arguments(kwargs, message):
    with pytest.raises(ValueError, match=message):
        _denoise(np.zeros((4, 4, 3)), **kwargs)
    with pytest.raises(ValueError, match=r"shape \(profiles, columns, 3\)"):
        _denoise(np.zeros((4, 3)))


def test_the_order_neighbours_are_tried_in_changes_nothing():
    """Neighbours are tried nearest first by the grid's pitch, for speed: any pitch gives the same
    bytes, and they are those of a plain sort of the window's distances."""
    from tasks.denoise import mean_knn_distance

    rng = np.random.default_rng(11)
    grid = np.stack(np.meshgrid(np.arange(40) * 0.02, np.arange(30) * 0.1), -1)[..., ::-1]
    points = np.concatenate([grid, rng.normal(0, 0.01, (30, 40, 1))], axis=-1)
    points[rng.random((30, 40)) < 0.1] = np.nan
    points[5, 7] += 3.0  # an outlier
    runs = [mean_knn_distance(points, k=6, window_rows=2, window_cols=3, pitch_mm=pitch)
            for pitch in ((0.1, 0.02), (1.0, 1.0), (0.02, 0.1), (5.0, 0.001))]
    assert all(np.array_equal(runs[0], r, equal_nan=True) for r in runs[1:])
    expected = np.full((30, 40), np.nan)
    for i in range(30):
        for j in range(40):
            if not np.isfinite(points[i, j]).all():
                continue
            window = points[max(i - 2, 0):i + 3, max(j - 3, 0):j + 4].reshape(-1, 3)
            d = np.sort(np.linalg.norm(window - points[i, j], axis=1))
            d = d[np.isfinite(d)][1:]  # the point itself (0) first
            if len(d) >= 6:
                expected[i, j] = np.sum(d[:6]) / 6
    np.testing.assert_allclose(runs[0], expected, rtol=1e-12, atol=1e-15)
    assert np.array_equal(np.isnan(runs[0]), np.isnan(expected))
