"""What the QA page shows, as numbers (tasks.qa_views, tasks.coverage), on known inputs: the view
frame recovers a known placement, the thinning keeps cells well sampled, the passes land where
their poses put them, the maps' scales and figures, the stickers on the image, the registration
graph's edges and rows, the mesh's weld-zone close-up. In-memory arrays; milliseconds."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from schemas.stage_documents import SurfacePair
from tasks.coverage import FaceAccumulator, FaceGrid, coverage_figures
from tasks.frames import apply, invert, rotate, rotation_deg, translation
from tasks.qa_views import (PairEdge, coverage_maps, mesh_in_view, overlap_edges, pass_in_view, pass_rows,
                            plan_view_lines, principal_axes_frame, registration_edges, sticker_marks, surface_view,
                            thinning_steps)
from tasks.weld_zone import weld_zone

# a known placement: box frame -> world
T_WORLD_BOX = translation([120.0, -35.0, 8.0]) @ rotation_deg("z", 33.0) @ rotation_deg("x", -12.0) @ rotation_deg("y", 5.0)


def _skewed_box(n: int = 20) -> np.ndarray:
    """(n**3, 3) points on a grid filling a 60 x 20 x 4 mm box, denser toward each axis's low end:
    a product of three axes, so their covariance is diagonal in the box frame, and a positive
    third moment along x, y and z, so the principal axes' signs are those of the box frame."""
    u = (np.arange(n) / (n - 1)) ** 2 - 0.5
    x, y, z = np.meshgrid(u * 60.0, u * 20.0, u * 4.0, indexing="ij")
    return np.c_[x.ravel(), y.ravel(), z.ravel()]


# --- the view frame ---
def test_the_principal_axes_frame_recovers_a_known_rotation_of_a_box():
    box = _skewed_box()
    T_view_world = principal_axes_frame(apply(T_WORLD_BOX, box))
    # view frame = the box frame moved to the points' centroid
    assert_allclose(T_view_world[:3, :3] @ T_WORLD_BOX[:3, :3], np.eye(3), atol=1e-9)
    assert_allclose(apply(T_view_world @ T_WORLD_BOX, box), box - box.mean(axis=0), atol=1e-9)


def test_the_principal_axes_frame_is_right_handed_whatever_the_skew():
    box = _skewed_box() * [1.0, 1.0, -1.0]  # z skewed the other way: its sign flips, then back for handedness
    R = principal_axes_frame(apply(T_WORLD_BOX, box))[:3, :3]
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    assert_allclose(R @ T_WORLD_BOX[:3, :3], np.diag([1.0, 1.0, 1.0]), atol=1e-9)


@pytest.mark.parametrize(("points", "message"), [
    (np.zeros((10, 2)), r"points_mm must be \(n, 3\)"),
    (np.zeros((2, 3)), "at least 3 finite points; got 2"),
    (np.r_[np.eye(3), [[np.nan, 0.0, 0.0]]], r"\(1 not finite\)"),
])
def test_the_principal_axes_frame_refuses_bad_points(points, message):
    with pytest.raises(ValueError, match=message):
        principal_axes_frame(points)


def test_a_placed_part_is_drawn_in_its_specimen_frame_and_only_its_measured_points():
    box = _skewed_box(10)
    normals = np.tile([0.0, 0.0, 1.0], (len(box), 1)).astype(np.float32)
    measured = np.arange(len(box)) % 3 != 0
    view = surface_view(apply(T_WORLD_BOX, box), rotate(T_WORLD_BOX, normals), measured,
                        T_common_specimen=T_WORLD_BOX)
    assert view.placed and view.points_mm.dtype == np.float64 and view.normals.dtype == np.float64
    assert_allclose(view.T_view_common, invert(T_WORLD_BOX), atol=1e-12)
    assert_allclose(view.points_mm, box[measured], atol=1e-9)
    assert_allclose(view.normals, np.tile([0.0, 0.0, 1.0], (measured.sum(), 1)), atol=1e-6)
    unplaced = surface_view(apply(T_WORLD_BOX, box), normals, measured, T_common_specimen=None)
    assert not unplaced.placed
    assert_allclose(unplaced.T_view_common, principal_axes_frame(apply(T_WORLD_BOX, box)[measured]))
    with pytest.raises(ValueError, match="the same n points"):
        surface_view(box, normals, measured[:-1], T_common_specimen=None)


def test_the_weld_lines_are_seen_from_above_in_the_view_frame():
    line = np.array([[0.0, -10.0, 2.0], [0.0, 10.0, 2.0]])
    (seen,) = plan_view_lines([apply(T_WORLD_BOX, line)], invert(T_WORLD_BOX))
    assert_allclose(seen, line[:, :2], atol=1e-9)


# --- the coverage maps ---
def test_the_thinning_step_keeps_grid_points_at_most_a_third_of_a_cell_apart():
    pitch = (0.05, 0.11)  # between profiles, between columns, mm
    steps = thinning_steps((4000, 900, 3), cell_mm=1.0, points_per_pass=200_000, grid_pitch_mm=pitch)
    assert steps == (6, 3)
    for k, p in zip(steps, pitch):
        assert k * p <= 1.0 / 3 < (k + 1) * p  # as coarse as keeps about nine points a cell
    assert thinning_steps((10, 10, 3), cell_mm=0.1, points_per_pass=1000, grid_pitch_mm=pitch) == (1, 1)


def test_an_imported_scan_is_thinned_evenly_to_about_the_points_asked_for():
    assert thinning_steps((1_000_000, 3), cell_mm=1.0, points_per_pass=200_000) == (5,)
    assert thinning_steps((150_000, 3), cell_mm=1.0, points_per_pass=200_000) == (1,)


@pytest.mark.parametrize(("shape", "kwargs", "message"), [
    ((100, 3), dict(cell_mm=0.0, points_per_pass=1000), "cell_mm must be positive"),
    ((100, 3), dict(cell_mm=1.0, points_per_pass=1000, grid_pitch_mm=(0.1, 0.1)), r"a grid pass is \(profiles"),
    ((10, 10, 3), dict(cell_mm=1.0, points_per_pass=1000, grid_pitch_mm=(0.1, 0.0)), "two positive pitches"),
])
def test_the_thinning_refuses_bad_inputs(shape, kwargs, message):
    with pytest.raises(ValueError, match=message):
        thinning_steps(shape, **kwargs)


def test_a_pass_lands_where_its_pose_puts_it_with_its_sweep_on_the_face_it_looked_at():
    grid = np.stack(np.meshgrid(np.arange(5.0), np.arange(4.0), indexing="ij"), axis=-1)
    points = np.concatenate([grid, np.zeros((5, 4, 1))], axis=-1).astype(np.float32)  # (profiles, columns, 3)
    normals = np.broadcast_to(np.array([0.0, 0.0, 1.0], np.float32), points.shape)
    origins = np.c_[np.arange(5.0), np.zeros(5), np.full(5, 100.0)]
    T_common_pass = translation([10.0, 0.0, 0.0])
    T_view_common = rotation_deg("x", 180.0)  # the view turned over: the pass looks at the bottom face
    seen = pass_in_view(points, normals, origins, T_view_common=T_view_common, T_common_pass=T_common_pass)
    assert seen.points_mm.shape == (20, 3) and seen.points_mm.dtype == np.float64
    assert_allclose(seen.points_mm, apply(T_view_common @ T_common_pass, points.reshape(-1, 3).astype(np.float64)))
    assert_allclose(seen.normals, np.tile([0.0, 0.0, -1.0], (20, 1)), atol=1e-12)
    assert seen.face == "bottom"
    assert_allclose(seen.sweep_mm, [[10.0, 0.0], [14.0, 0.0]], atol=1e-12)
    up = pass_in_view(points, normals, origins, T_view_common=np.eye(4), T_common_pass=np.eye(4))
    assert up.face == "top"
    origins[-1] = np.nan
    unknown = pass_in_view(points, normals, origins, T_view_common=np.eye(4), T_common_pass=np.eye(4))
    assert unknown.sweep_mm is None and unknown.face is None
    with pytest.raises(ValueError, match=r"T_common_pass must be a \(4, 4\) pose"):
        pass_in_view(points, normals, origins, T_view_common=np.eye(4), T_common_pass=np.eye(3))


def _grids() -> list[FaceGrid]:
    passes = np.array([[0, 1], [2, 3]])
    spread = np.array([[np.nan, np.nan], [0.010, 0.030]])
    return [FaceGrid("top", passes, spread, (0.0, 0.0), 1.0),
            FaceGrid("bottom", np.zeros((2, 2), int), np.full((2, 2), np.nan), (0.0, 0.0), 1.0)]


def test_the_maps_show_passes_per_cell_and_their_spread_in_um_with_known_scales():
    maps = coverage_maps(_grids())
    top = maps.coverage[0]
    assert top.name == "top face: passes that measured each 1 mm cell"
    assert_allclose(top.values, [[np.nan, 1.0], [2.0, 3.0]])
    assert np.isnan(maps.coverage[1].values).all()
    assert_allclose(maps.spread[0].values, [[np.nan, np.nan], [10.0, 30.0]])
    assert maps.most_passes == 3
    assert maps.spread_top_um == pytest.approx(29.8)  # the 99th percentile of 10 and 30 um
    figures = coverage_figures(_grids())
    assert (figures.cells_seen, figures.cells_two_or_more) == (3, 2)
    assert (figures.disagreement_median_um, figures.disagreement_p95_um, figures.disagreement_max_um) == (20.0, 29.0, 30.0)


def test_maps_with_no_overlap_have_no_disagreement_figures_and_a_unit_scale():
    lonely = [FaceGrid("top", np.array([[1]]), np.array([[np.nan]]), (0.0, 0.0), 1.0)]
    assert coverage_maps(lonely).spread_top_um == 1.0
    assert coverage_figures(lonely).disagreement_median_um is None
    with pytest.raises(ValueError, match="at least one face"):
        coverage_maps([])


def test_the_coverage_grid_covers_the_surface_and_two_cells_round_it():
    surface = np.array([[0.0, 0.0, 0.0], [10.0, 4.0, 0.0]])
    faces = FaceAccumulator.around(surface, np.tile([0.0, 0.0, 1.0], (2, 1)), cell_mm=0.5)
    assert faces.origin == (-1.0, -1.0)
    assert (faces.cols, faces.rows) == (24, 12)  # (10 + 2) / 0.5, (4 + 2) / 0.5
    with pytest.raises(ValueError, match=r"surface_mm must be \(m >= 1, 3\)"):
        FaceAccumulator.around(np.zeros((0, 3)), np.zeros((0, 3)), cell_mm=0.5)


# --- the stickers ---
def test_the_stickers_are_drawn_at_their_pixels_centres_in_mm():
    pixel = np.array([[0.0, 0.0], [9.0, 3.0]])  # (profile, column)
    marks = sticker_marks(pixel, np.array([0.010, 0.030]), grid_spacing_mm=(0.2, 0.05), grid_shape=(100, 40))
    assert marks.extent_mm == (0.0, 2.0, 0.0, 20.0)
    assert_allclose(marks.centres_mm, [[0.025, 0.1], [0.175, 1.9]])  # (along the line, along the sweep)
    assert marks.median_rms_um == pytest.approx(20.0)
    none = sticker_marks(np.zeros((0, 2)), np.zeros(0), grid_spacing_mm=(0.2, 0.05), grid_shape=(100, 40))
    assert none.median_rms_um is None and none.centres_mm.shape == (0, 2)
    with pytest.raises(ValueError, match="must agree"):
        sticker_marks(pixel, np.zeros(3), grid_spacing_mm=(0.2, 0.05), grid_shape=(100, 40))


# --- the registration graph ---
def test_the_graph_joins_pass_pairs_by_their_inlier_targets_median_residual():
    edge_passes = np.array([[0, 1], [1, 0], [1, 0], [2, 1], [0, 2]])
    residual = np.array([0.010, 0.020, 0.060, 0.005, 0.500])
    inlier = np.array([True, True, True, True, False])
    edges = registration_edges(edge_passes, residual, inlier)
    assert edges == [PairEdge(0, 1, 3, 0.020), PairEdge(1, 2, 1, 0.005)]  # (0, 2): an outlier only
    rows = pass_rows(["a", "b", "c"], ["s1", "s1", "s2"], edges, {"a": 0.0123, "b": None})
    assert [(r.pass_id, r.setup, r.pairs, r.rms_um) for r in rows] == [("a", "s1", 1, 12.3), ("b", "s1", 2, None),
                                                                      ("c", "s2", 1, None)]
    with pytest.raises(ValueError, match="must agree"):
        registration_edges(edge_passes, residual[:-1], inlier)
    with pytest.raises(ValueError, match="3 passes but 2 setups"):
        pass_rows(["a", "b", "c"], ["s1", "s1"], edges, {})


def test_the_surface_overlaps_are_edges_between_known_passes():
    pairs = [SurfacePair(a="b", b="c", points=900, rms_mm=0.004), SurfacePair(a="a", b="x", points=900, rms_mm=0.1),
             SurfacePair(a="c", b="a", points=0, rms_mm=None)]
    edges = overlap_edges(["a", "b", "c"], pairs)
    assert [e[:2] for e in edges] == [(1, 2), (2, 0)]
    assert edges[0].rms_mm == 0.004 and math.isnan(edges[1].rms_mm)


# --- the mesh ---
def _plate_faces(z: float, up: bool, n: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """A flat n x n mm grid at height z, its triangles facing up (or down)."""
    x, y = np.meshgrid(np.arange(n + 1.0), np.arange(n + 1.0), indexing="xy")
    vertices = np.c_[x.ravel(), y.ravel(), np.full(x.size, z)]
    k = (np.arange(n)[None, :] + (n + 1) * np.arange(n)[:, None]).ravel()
    tri = np.r_[np.c_[k, k + 1, k + n + 2], np.c_[k, k + n + 2, k + n + 1]]
    return vertices, tri if up else tri[:, ::-1]


def test_the_close_up_is_the_weld_zones_upward_faces_seen_along_the_weld():
    top, top_tri = _plate_faces(1.0, up=True)
    bottom, bottom_tri = _plate_faces(-1.0, up=False)
    vertices, triangles = np.r_[top, bottom], np.r_[top_tri, bottom_tri + len(top)]
    zone = weld_zone([np.array([[5.0, 0.0, 1.0], [5.0, 10.0, 1.0]])], 1.5)  # along y on the top face
    T_view_common = translation([0.0, 0.0, 3.0])
    seen = mesh_in_view(vertices, triangles, zone=zone, T_view_common=T_view_common)
    assert_allclose(seen.vertices_mm, vertices + [0.0, 0.0, 3.0])
    assert seen.zone_radius_mm == 1.5
    assert_allclose(seen.in_zone, zone.faces_in(vertices, triangles))
    assert not seen.in_zone[len(top_tri):].any() and seen.in_zone[:len(top_tri)].sum() == 60
    close = seen.close_up
    assert close is not None and len(close.triangles) == 60 and close.in_zone.all()
    assert_allclose(close.vertices_mm[close.triangles], seen.vertices_mm[triangles[seen.in_zone]])
    assert close.azimuth_deg == pytest.approx(90.0 + 200.0)  # the line runs along +y


def test_no_weld_zone_no_close_up():
    vertices, triangles = _plate_faces(0.0, up=True)
    seen = mesh_in_view(vertices, triangles, zone=weld_zone([], 1.0), T_view_common=np.eye(4))
    assert seen.zone_radius_mm == 0.0 and not seen.in_zone.any() and seen.close_up is None
    with pytest.raises(ValueError, match=r"triangles must be \(n, 3\)"):
        mesh_in_view(vertices, triangles[:, :2], zone=weld_zone([], 1.0), T_view_common=np.eye(4))

