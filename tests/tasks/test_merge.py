"""Box-grid merge: per-cell means on an origin-aligned grid, checked against Open3D's voxel filter."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from tasks.merge import merge_box_grid


def _sorted_by_cell(points: np.ndarray, cell: float, *others: np.ndarray):
    """Rows sorted by the (i, j, k) cell holding each point (a cell mean lies in its cell)."""
    ijk = np.floor(points / cell).astype(np.int64)
    order = np.lexsort(ijk.T[::-1])
    return (points[order], *(o[order] for o in others))


def _open3d_merge(points: np.ndarray, cell: float, normals: np.ndarray | None = None):
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    if normals is not None:
        cloud.normals = o3d.utility.Vector3dVector(normals)
    down = cloud.voxel_down_sample(cell)
    return np.asarray(down.points), np.asarray(down.normals)


def _random_cloud(rng, n, low, high):
    points = rng.uniform(low, high, (n, 3))
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return points, normals


def test_matches_open3d_when_its_grid_corner_is_on_the_origin_grid():
    # Open3D's grid starts at min_bound - cell / 2: a point at (cell / 2,) * 3 as the minimum puts
    # that corner at the origin, so both grids coincide exactly (cell 0.5 keeps the arithmetic exact).
    rng = np.random.default_rng(1)
    cell = 0.5
    points, normals = _random_cloud(rng, 200_000, cell / 2, 10.0)
    points[0] = cell / 2
    ours = merge_box_grid(points, cell_mm=cell, normals=normals)
    theirs, their_normals = _open3d_merge(points, cell, normals)
    assert len(theirs) == ours.n_points == 8000  # 20^3 occupied cells (dense data)
    assert ours.counts.sum() == len(points)
    theirs, their_normals = _sorted_by_cell(theirs, cell, their_normals)
    assert np.abs(theirs - ours.points_mm).max() < 1e-9
    # Open3D 0.20 averages normals without renormalising them; we renormalise.
    their_normals /= np.linalg.norm(their_normals, axis=1, keepdims=True)
    assert np.abs(their_normals - ours.normals).max() < 1e-9
    np.testing.assert_allclose(np.linalg.norm(ours.normals, axis=1), 1.0, atol=1e-12)


def test_matches_open3d_on_sparse_data_once_shifted_to_its_grid():
    # Any cell and any offset: shifting the points by Open3D's grid corner makes the grids agree.
    rng = np.random.default_rng(2)
    cell = 0.37
    points, _ = _random_cloud(rng, 50_000, -31.3, 17.9)  # sparse: most cells hold 1-2 points
    corner = points.min(axis=0) - cell / 2
    ours = merge_box_grid(points - corner, cell_mm=cell)
    theirs, _ = _open3d_merge(points, cell)
    assert len(theirs) == ours.n_points
    assert ours.n_points < len(points) and ours.counts.max() >= 2  # some cells really were merged
    theirs = _sorted_by_cell(theirs - corner, cell)[0]
    assert np.abs(theirs - ours.points_mm).max() < 1e-9


def test_grid_is_origin_aligned_unlike_open3d():
    points = np.array([[0.1, 0.1, 0.1], [0.9, 0.1, 0.1], [1.1, 0.1, 0.1]])
    ours = merge_box_grid(points, cell_mm=1.0)
    np.testing.assert_allclose(ours.points_mm, [[0.5, 0.1, 0.1], [1.1, 0.1, 0.1]], atol=1e-15)
    np.testing.assert_array_equal(ours.cells, [[0, 0, 0], [1, 0, 0]])
    np.testing.assert_array_equal(ours.counts, [2, 1])
    theirs, _ = _open3d_merge(points, 1.0)  # Open3D's cells start at x = 0.1 - 0.5
    np.testing.assert_allclose(_sorted_by_cell(theirs, 1.0)[0], [[0.1, 0.1, 0.1], [1.0, 0.1, 0.1]], atol=1e-15)


def test_deterministic_sensors_averaged_and_cancelling_normals_are_nan():
    rng = np.random.default_rng(3)
    points = rng.uniform(-5, 5, (5000, 3))
    sensors = points + np.array([0.0, 0.0, 300.0])
    ours = merge_box_grid(points, cell_mm=1.0, sensor_positions_mm=sensors)
    order = rng.permutation(len(points))
    shuffled = merge_box_grid(points[order], cell_mm=1.0, sensor_positions_mm=sensors[order])
    np.testing.assert_array_equal(ours.cells, shuffled.cells)
    np.testing.assert_allclose(ours.points_mm, shuffled.points_mm, atol=1e-12)
    np.testing.assert_allclose(ours.sensor_positions_mm, ours.points_mm + [0, 0, 300], atol=1e-9)
    assert ours.normals is None
    keys = ours.cells[:, 0] * 10**8 + ours.cells[:, 1] * 10**4 + ours.cells[:, 2]
    assert np.all(np.diff(keys) > 0)  # sorted by (i, j, k)
    cancel = merge_box_grid(np.array([[0.2, 0.2, 0.2], [0.3, 0.3, 0.3]]), cell_mm=1.0,
                            normals=np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]))
    assert np.isnan(cancel.normals).all()


@pytest.mark.parametrize(
    ("args", "kwargs", "message"),
    [((np.zeros((4, 2)),), {"cell_mm": 1.0}, r"points_mm must have shape \(n, 3\)"),
     ((np.full((4, 3), np.nan),), {"cell_mm": 1.0}, "points_mm holds NaN"),
     ((np.zeros((4, 3)),), {"cell_mm": 0.0}, "cell_mm must be positive"),
     ((np.zeros((4, 3)),), {"cell_mm": 1.0, "normals": np.zeros((3, 3))},
      r"normals must have one row per point \(4\)"),
     ((np.zeros((4, 3)),), {"cell_mm": 1.0, "sensor_positions_mm": np.zeros((4, 4))},
      "sensor_positions_mm must have shape")],
)
def test_bad_arguments(args, kwargs, message):
    with pytest.raises(ValueError, match=message):
        merge_box_grid(*args, **kwargs)


def test_partial_cell_sums_combine_to_the_in_memory_merge():
    """Out of core: blocks summed per cell, the partial sums combined later (in any grouping that
    keeps each cell's partials together) give the in-memory merge's cells and counts, and its
    means to the last few bits (another summation order)."""
    from tasks.merge import CellSums, cell_sums, combine_cell_sums

    rng = np.random.default_rng(7)
    points, normals = _random_cloud(rng, 300_000, -20.0, 20.0)
    whole = merge_box_grid(points, cell_mm=0.5, normals=normals)
    parts = [cell_sums(points[a:a + 37_000], normals[a:a + 37_000], cell_mm=0.5) for a in range(0, len(points), 37_000)]
    joined = CellSums(*(np.concatenate([getattr(p, f) for p in parts])
                        for f in ("keys", "counts", "point_sums", "normal_sums")))
    merged = combine_cell_sums(joined, cell_mm=0.5)
    np.testing.assert_array_equal(merged.cells, whole.cells)
    np.testing.assert_array_equal(merged.counts, whole.counts)
    np.testing.assert_allclose(merged.points_mm, whole.points_mm, rtol=0, atol=1e-12)
    np.testing.assert_allclose(merged.normals, whole.normals, rtol=0, atol=1e-9)
    # the same parts in the same order give the same bytes
    again = combine_cell_sums(joined, cell_mm=0.5)
    assert again.points_mm.tobytes() == merged.points_mm.tobytes()


def test_flat_cells_coarsen_and_bent_cells_stay_fine():
    """A plate with a 1 mm-radius groove (a weld toe's curvature) across it: the flat plate merges
    into coarse cells, the groove keeps its fine cells; each coarse point is the mean of all the
    points it holds, and nothing is lost (counts add up)."""
    from tasks.merge import coarsen_flat_cells

    rng = np.random.default_rng(3)
    xy = rng.uniform(0.0, 20.0, (400_000, 2))
    x = xy[:, 0]
    groove = np.abs(x - 10.0) < 0.9  # a circular groove of radius 1 mm, 0.56 mm deep at its centre
    z = np.where(groove, 1.0 - np.sqrt(np.clip(1.0 - (x - 10.0) ** 2, 0, None)) - (1 - np.sqrt(1 - 0.81)), 0.0)
    points = np.column_stack([xy, z + rng.normal(0, 0.001, len(z))])
    gx = np.where(groove, -(x - 10.0), 0.0)  # the groove's normal: toward its centre line, upward
    normals = np.column_stack([gx, np.zeros(len(x)), np.where(groove, np.sqrt(np.clip(1 - gx**2, 0, None)), 1.0)])
    fine = merge_box_grid(points, cell_mm=0.1, normals=normals)
    result = coarsen_flat_cells(fine, factor=4, max_normal_deg=4.0, max_deviation_mm=0.01)
    assert result.counts.sum() == fine.counts.sum() == len(points)
    coarse_x = result.points_mm[~result.fine, 0]
    fine_x = result.points_mm[result.fine, 0]
    assert np.all(np.abs(coarse_x - 10.0) > 0.4)  # no coarse cell inside the groove
    assert np.all(np.abs(fine_x - 10.0) < 1.7)  # the fine cells lie at the groove (and its rim cells)
    assert (~result.fine).sum() > 0.8 * 20 * 20 / 0.4**2 * (18 / 20)  # the plate is coarse
    # a coarse point is the mean of the measured points in its coarse cell
    cell = np.floor(points / 0.4).astype(np.int64)
    probe = result.points_mm[~result.fine][0]
    inside = np.all(cell == np.floor(probe / 0.4).astype(np.int64), axis=1)
    np.testing.assert_allclose(probe, points[inside].mean(axis=0), atol=1e-12)
    # factor 1: the fine cloud unchanged
    same = coarsen_flat_cells(fine, factor=1, max_normal_deg=4.0, max_deviation_mm=0.01)
    assert same.fine.all() and np.array_equal(same.points_mm, fine.points_mm)


def test_cells_in_a_weld_line_zone_stay_fine_even_where_flat():
    """The weld's zone from the manifest: the zone round a line across a flat plate keeps its fine
    cells; outside it the plate coarsens as before, and nothing is lost."""
    from tasks.merge import coarsen_flat_cells
    from tasks.weld_zone import PolylineZone, WeldZone

    rng = np.random.default_rng(4)
    points = np.column_stack([rng.uniform(0.0, 20.0, (200_000, 2)), rng.normal(0, 0.001, 200_000)])
    normals = np.tile([0.0, 0.0, 1.0], (len(points), 1))
    fine = merge_box_grid(points, cell_mm=0.1, normals=normals)
    zone = PolylineZone(points_mm=((10.0, -1.0, 0.0), (10.0, 21.0, 0.0)), radius_mm=2.0)
    plain = coarsen_flat_cells(fine, factor=4, max_normal_deg=4.0, max_deviation_mm=0.01)
    zoned = coarsen_flat_cells(fine, factor=4, max_normal_deg=4.0, max_deviation_mm=0.01, fine_zone=WeldZone((zone,)))
    assert plain.fine.sum() < 0.01 * len(plain.fine) and not plain.in_zone.any()
    assert zoned.counts.sum() == len(points)
    x = zoned.points_mm[:, 0]
    # a coarse cell (0.4 mm) is in the zone when its mean is: its fine cells reach 0.2 mm further
    assert np.all(zoned.fine[np.abs(x - 10.0) <= 1.8])
    assert np.all(~zoned.fine[np.abs(x - 10.0) > 2.4])
    assert np.array_equal(zoned.in_zone, zoned.fine)
    inside = np.abs(fine.points_mm[:, 0] - 10.0) <= 1.8
    assert zoned.fine.sum() >= inside.sum()


def test_polyline_zone_distance_against_brute_force():
    """The zone's distance to a bent 3-D polyline (a fillet weld's toe round a corner) equals the
    least distance to a dense sampling of its segments, inside and outside the zone's bounding
    box; ``contains`` is that distance against the radius."""
    from scipy.spatial import cKDTree

    from tasks.weld_zone import PolylineZone

    rng = np.random.default_rng(7)
    vertices = np.array([[0.0, 0.0, 0.0], [30.0, 0.0, 5.0], [30.0, 40.0, 5.0], [10.0, 60.0, -5.0]])
    zone = PolylineZone(tuple(map(tuple, vertices.tolist())), radius_mm=6.0)
    probe = rng.uniform([-20, -20, -20], [50, 80, 20], (4000, 3))
    t = np.linspace(0.0, 1.0, 20_001)[:, None]
    dense = np.concatenate([a + t * (b - a) for a, b in zip(vertices[:-1], vertices[1:])])
    brute = cKDTree(dense[::4]).query(probe)[0]  # the least distance to every sample (exact, not approximate)
    step = max(np.linalg.norm(np.diff(vertices, axis=0), axis=1)) / 5000  # the sampling's spacing
    got = zone.distance_mm(probe)
    assert np.all(got <= brute + 1e-9) and np.all(brute - got <= step)
    clear = np.abs(brute - zone.radius_mm) > step
    assert np.array_equal(zone.contains(probe)[clear], (brute <= zone.radius_mm)[clear])
    assert 100 < zone.contains(probe).sum() < 3900  # both sides of the radius are probed


def test_polyline_projection_gives_the_station_along_the_line():
    """An L-shaped line, 10 mm along x then 5 mm along y: a point's station is the arc length to
    its closest point on the line, its distance the same as the zone's."""
    from tasks.weld_zone import PolylineZone, polyline_projection

    line = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [10.0, 5.0, 0.0]])
    points = np.array([[3.0, 1.0, 0.0], [12.0, 4.0, 0.0], [-2.0, 0.0, 0.0], [10.0, 9.0, 2.0]])
    distance, station = polyline_projection(points, line)
    np.testing.assert_allclose(station, [3.0, 14.0, 0.0, 15.0])
    np.testing.assert_allclose(distance, [1.0, 2.0, 2.0, np.hypot(4.0, 2.0)])
    zone = PolylineZone(tuple(map(tuple, line)), 1.0)
    assert np.array_equal(zone.distance_mm(points), distance)
