"""Specimen segmentation: a plate, a fixture block 10 mm below it and a base plane 40 mm below."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from tasks.segment import keep_specimen_components

SPACING = 0.5
LINK = 0.8  # above the 0.5 mm spacing (and its 0.71 mm diagonal), far below the 10 mm gaps


def _grid(a: float, b: float) -> np.ndarray:
    u, v = np.meshgrid(np.arange(0.0, a + 1e-9, SPACING), np.arange(0.0, b + 1e-9, SPACING), indexing="ij")
    return np.stack([u.ravel(), v.ravel()], axis=1)


def _box_surface(lo, size) -> np.ndarray:
    """Points on the six faces of an axis-aligned box, SPACING apart (edges shared: duplicates kept)."""
    sx, sy, sz = size
    faces = []
    for axis, (a, b) in enumerate([(sy, sz), (sx, sz), (sx, sy)]):
        uv = _grid(a, b)
        others = [i for i in range(3) if i != axis]
        for level in (0.0, size[axis]):
            face = np.empty((len(uv), 3))
            face[:, axis] = level
            face[:, others] = uv
            faces.append(face)
    return np.concatenate(faces) + np.asarray(lo, float)


@pytest.fixture(scope="module")
def scene():
    plate = _box_surface((0, 0, 0), (100, 50, 5))
    block = _box_surface((40, 15, -18), (20, 20, 8))  # its top is 10 mm below the plate
    uv = _grid(160, 110)
    base = np.column_stack([uv[:, 0] - 30, uv[:, 1] - 30, np.full(len(uv), -40.0)])
    points = np.concatenate([base, plate, block])  # plate not first: labels must not depend on it
    part = np.repeat([0, 1, 2], [len(base), len(plate), len(block)])  # base, plate, block
    order = np.random.default_rng(0).permutation(len(points))
    return points[order], part[order]


def test_a_target_on_the_plate_keeps_only_the_plate(scene):
    points, part = scene
    targets = np.array([[50.0, 25.0, 5.3], [500.0, 0.0, 0.0]])  # a sticker centre 0.3 mm above the top; one far off
    result = keep_specimen_components(points, link_mm=LINK, target_points_mm=targets)
    assert result.n_components == 3
    np.testing.assert_array_equal(result.keep, part == 1)
    np.testing.assert_array_equal(result.target_hit, [True, False])
    assert result.kept_counts.tolist() == [np.count_nonzero(part == 1)]
    # each part is one component; labels are numbered by size: base (largest) 0, plate 1, block 2
    for p, label in [(0, 0), (1, 1), (2, 2)]:
        assert set(result.labels[part == p].tolist()) == {label}
    np.testing.assert_allclose(result.extent_mm, [160.0, 100.0, 20.0])


def test_min_extent_keeps_the_big_components(scene):
    points, part = scene
    result = keep_specimen_components(points, link_mm=LINK, min_extent_mm=60.0)
    np.testing.assert_array_equal(result.keep, part != 2)
    np.testing.assert_array_equal(result.kept_labels, [0, 1])
    assert result.target_hit is None
    result = keep_specimen_components(points, link_mm=LINK, min_extent_mm=120.0)
    np.testing.assert_array_equal(result.keep, part == 0)


def test_a_link_longer_than_the_gap_joins_two_sheets():
    top = np.column_stack([_grid(10, 10), np.zeros(441)])
    below = top - [0.0, 0.0, 2.0]
    points = np.concatenate([top, below])
    apart = keep_specimen_components(points, link_mm=1.0, target_points_mm=[[5.0, 5.0, 0.0]])
    assert apart.n_components == 2 and apart.keep.sum() == 441
    joined = keep_specimen_components(points, link_mm=2.1, target_points_mm=[[5.0, 5.0, 0.0]])
    assert joined.n_components == 1 and joined.keep.all()


def test_cell_components_coarsen_open3d_dbscan_with_one_point():
    """Open3D's components at eps = link (points within link linked) each lie inside one of ours
    (cells touching); ours join points at most 2*sqrt(3)*link apart, so DBSCAN at that eps joins
    at least as much as ours."""
    rng = np.random.default_rng(5)
    points = rng.uniform(0, 60, (4000, 3))  # sparse random points: many components of all sizes
    link = 1.5
    result = keep_specimen_components(points, link_mm=link, min_extent_mm=0.0)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    fine = np.asarray(cloud.cluster_dbscan(link, 1))
    coarse = np.asarray(cloud.cluster_dbscan(2 * np.sqrt(3) * link + 1e-9, 1))
    assert fine.max() + 1 >= result.n_components >= coarse.max() + 1
    assert result.n_components > 100
    for theirs in (fine,):  # each fine component maps into exactly one of ours
        pairs = np.unique(np.stack([theirs, result.labels], axis=1), axis=0)
        assert len(pairs) == theirs.max() + 1
    pairs = np.unique(np.stack([result.labels, coarse], axis=1), axis=0)
    assert len(pairs) == result.n_components  # each of ours inside one coarse component
    assert result.keep.all()


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [({"link_mm": 1.0}, "give target_points_mm or min_extent_mm"),
     ({"link_mm": 1.0, "min_extent_mm": 5.0, "target_points_mm": np.zeros((1, 3))}, "only one of"),
     ({"link_mm": 0.0, "min_extent_mm": 5.0}, "link_mm must be positive"),
     ({"link_mm": 1.0, "target_points_mm": np.zeros((0, 3))}, "target_points_mm is empty"),
     ({"link_mm": 1.0, "target_points_mm": np.zeros((2, 2))}, r"target_points_mm must have shape \(n, 3\)"),
     ({"link_mm": 1.0, "min_extent_mm": float("nan")}, "min_extent_mm must be"),
     ({"link_mm": 1.0, "min_extent_mm": 5.0, "points_mm": np.zeros((0, 3))}, "points_mm is empty"),
     ({"link_mm": 1.0, "min_extent_mm": 5.0, "points_mm": np.full((3, 3), np.inf)}, "points_mm holds NaN or inf")],
)
def test_bad_arguments(kwargs, message):
    points = kwargs.pop("points_mm", np.zeros((4, 3)))
    with pytest.raises(ValueError, match=message):
        keep_specimen_components(points, **kwargs)
