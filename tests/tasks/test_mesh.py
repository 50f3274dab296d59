"""Surface: normals toward the sensor, screened Poisson on a sphere and a box, the edge-based mesh
report, density trimming that must not silently open the mesh, STL/PLY export, and the same bytes
whatever the thread count."""

from __future__ import annotations

import ctypes
import hashlib
import json
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from schemas.reconstruction import PoissonConfig
from tasks.mesh import (
    _canonical_order,
    estimate_normals,
    mesh_report,
    screened_poisson,
    write_mesh,
)

REPO = Path(__file__).resolve().parents[2]
RADIUS = 20.0
SPHERE_VOLUME = 4.0 / 3.0 * np.pi * RADIUS**3
CFG = PoissonConfig()
POISSON = {"samples_per_node": CFG.samples_per_node, "point_weight": CFG.point_weight, "scale": CFG.poisson_scale}


def _sphere_directions(n: int) -> np.ndarray:
    """n near-uniform unit vectors (Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    polar = np.arccos(1.0 - 2.0 * i / n)
    azimuth = np.pi * (1.0 + 5.0**0.5) * i
    return np.column_stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)])


def _box_samples(size, step):
    """Points step apart on the faces of a box centred at the origin, with outward normals."""
    size = np.asarray(size, float)
    points, normals = [], []
    for axis in range(3):
        u, v = [i for i in range(3) if i != axis]
        a, b = np.meshgrid(np.arange(step / 2, size[u], step), np.arange(step / 2, size[v], step), indexing="ij")
        for side in (0.0, 1.0):
            p = np.zeros((a.size, 3))
            p[:, u], p[:, v], p[:, axis] = a.ravel(), b.ravel(), side * size[axis]
            n = np.zeros_like(p)
            n[:, axis] = 1.0 if side else -1.0
            points.append(p)
            normals.append(n)
    return np.concatenate(points) - size / 2, np.concatenate(normals)


def _surface_digests(stl_path) -> dict:
    """sha256 of the normals, the Poisson mesh and its STL file for a noisy scanned box (60 x 30 x
    10 mm, 5,400 points, 0.01 mm noise, oblique sensors 50 mm off the faces), config settings,
    depth 7 (9,280 vertices; depth 8 on 21,600 points took twice as long for the same question)."""
    points, outward = _box_samples([60.0, 30.0, 10.0], 1.0)
    rng = np.random.default_rng(3)
    points = points + rng.normal(0.0, 0.01, points.shape)
    sensors = points + 50.0 * outward + rng.uniform(-20.0, 20.0, points.shape)
    normals = estimate_normals(points, sensors, k=100)  # the paper's k
    result = screened_poisson(points, normals, depth=7, **POISSON)
    write_mesh(stl_path, result.vertices, result.triangles)
    arrays = {"normals": normals, "vertices": result.vertices, "triangles": result.triangles,
              "vertex_density": result.vertex_density}
    digests = {name: hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest() for name, a in arrays.items()}
    return {**digests, "stl": hashlib.sha256(Path(stl_path).read_bytes()).hexdigest(),
            "watertight": result.report.watertight}


@pytest.fixture(scope="module")
def unit_box():
    mesh = o3d.geometry.TriangleMesh.create_box(1.0, 1.0, 1.0)
    return np.asarray(mesh.vertices).copy(), np.asarray(mesh.triangles).astype(np.int64)


def test_sphere_depth_7_is_closed_and_accurate():
    directions = _sphere_directions(25_000)
    result = screened_poisson(RADIUS * directions, directions, depth=7, **POISSON)
    report = result.report
    assert report.watertight and report.consistently_oriented, report
    assert report.n_boundary_edges == 0 and report.n_non_manifold_edges == 0
    assert result.vertices.dtype == np.float64 and result.triangles.dtype == np.int64
    assert report.n_triangles == len(result.triangles) == 2 * report.n_vertices - 4  # closed genus-0 surface
    radial_error = np.abs(np.linalg.norm(result.vertices, axis=1) - RADIUS)
    assert radial_error.max() < 0.1, radial_error.max()  # measured 0.008 mm
    assert abs(report.volume_mm3 / SPHERE_VOLUME - 1) < 0.02, report.volume_mm3  # measured -0.02 %
    assert abs(report.surface_area_mm2 / (4 * np.pi * RADIUS**2) - 1) < 0.02
    assert result.note == "" and not result.trimmed


def test_output_order_is_canonical():
    # screened_poisson puts MeshLab's output in this order, which follows from the geometry alone;
    # tested on a shuffled mesh.
    directions = _sphere_directions(4000)
    result = screened_poisson(RADIUS * directions, directions, depth=5, **POISSON)
    rng = np.random.default_rng(7)
    perm = rng.permutation(len(result.vertices))
    inverse = np.argsort(perm)
    shuffled = inverse[result.triangles][rng.permutation(len(result.triangles))]
    shuffled = np.roll(shuffled, 1, axis=1)  # same winding, another first corner
    vertices, triangles, density = _canonical_order(result.vertices[perm], shuffled, result.vertex_density[perm])
    np.testing.assert_array_equal(vertices, result.vertices)
    np.testing.assert_array_equal(triangles, result.triangles)
    np.testing.assert_array_equal(density, result.vertex_density)


def test_box_depth_7_is_closed_with_the_right_volume():
    size = np.array([60.0, 30.0, 10.0])
    points, normals = _box_samples(size, 0.5)
    result = screened_poisson(points, normals, depth=7, **POISSON)
    assert result.report.watertight and result.report.consistently_oriented, result.report
    assert abs(result.report.volume_mm3 / size.prod() - 1) < 0.02, result.report.volume_mm3  # measured -0.1 %
    # distance of each vertex to the box surface; Poisson rounds the edges slightly
    q = np.abs(result.vertices) - size / 2
    distance = np.abs(np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0))
    assert distance.max() < 0.2, distance.max()  # measured 0.14 mm, at the edges
    away_from_edges = (np.abs(q) < 2.0).sum(axis=1) <= 1
    assert distance[away_from_edges].max() < 0.05  # measured 0.011 mm


def test_same_bytes_for_any_thread_count_process_and_thread(tmp_path):
    # Fresh processes with 1, 2 and 4 OpenMP/BLAS threads, all at once (so on busy cores), and this
    # process in a worker thread (as the flow runs stages), must give the same bytes to the STL.
    script = ("import json, sys; from tests.tasks.test_mesh import _surface_digests; "
              "open(sys.argv[2], 'w').write(json.dumps(_surface_digests(sys.argv[1])))")
    runs = {}
    for n in (1, 2, 4):
        env = dict(os.environ, OMP_NUM_THREADS=str(n), OPENBLAS_NUM_THREADS=str(n), MKL_NUM_THREADS=str(n))
        args = [sys.executable, "-c", script, str(tmp_path / f"{n}.stl"), str(tmp_path / f"{n}.json")]
        runs[n] = subprocess.Popen(args, cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                   text=True)
    with ThreadPoolExecutor(max_workers=1) as pool:
        here = pool.submit(_surface_digests, tmp_path / "here.stl").result()
    assert here["watertight"]
    for n, run in runs.items():
        _, stderr = run.communicate(timeout=120)
        assert run.returncode == 0, stderr[-2000:]
        there = json.loads((tmp_path / f"{n}.json").read_text())
        assert there == here, f"OMP_NUM_THREADS={n}: {[k for k in here if there[k] != here[k]]} differ"


def test_poisson_restores_the_callers_openmp_thread_count():
    try:
        gomp = ctypes.CDLL("libgomp.so.1", mode=os.RTLD_NOLOAD)  # pymeshlab's OpenMP runtime
    except (OSError, AttributeError):
        pytest.skip("no libgomp in this process")
    before = gomp.omp_get_max_threads()
    gomp.omp_set_num_threads(3)
    try:
        directions = _sphere_directions(2000)
        screened_poisson(RADIUS * directions, directions, depth=5, **POISSON)  # runs on one thread
        assert gomp.omp_get_max_threads() == 3
    finally:
        gomp.omp_set_num_threads(before)


def test_estimated_normals_point_to_the_sensor():
    directions = _sphere_directions(8000)
    points = RADIUS * directions
    corners = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T * 60.0  # 8 outside sensors
    seen_by = np.argmax(directions @ corners.T, axis=1)
    normals = estimate_normals(points, corners[seen_by], k=12)
    cosine = np.einsum("ij,ij->i", normals, directions)
    assert cosine.min() > 0.99, cosine.min()  # right sign everywhere, and accurate
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-9)
    inward = estimate_normals(points, np.zeros_like(points), k=12)  # a sensor at the centre
    assert np.einsum("ij,ij->i", inward, directions).max() < -0.99


def test_report_of_closed_and_open_meshes(unit_box):
    vertices, triangles = unit_box
    closed = mesh_report(vertices, triangles)
    assert closed.watertight and closed.consistently_oriented
    assert closed.volume_mm3 == pytest.approx(1.0, abs=1e-12) and closed.surface_area_mm2 == pytest.approx(6.0)
    assert (closed.n_vertices, closed.n_triangles, closed.n_boundary_edges) == (8, 12, 0)
    assert mesh_report(vertices, triangles[:, ::-1]).volume_mm3 == pytest.approx(-1.0)  # inside out

    single = mesh_report(np.eye(3), np.array([[0, 1, 2]]))
    assert not single.watertight and single.n_boundary_edges == 3 and single.consistently_oriented
    assert single.surface_area_mm2 == pytest.approx(np.sqrt(3) / 2)

    corner = vertices[triangles]
    normals = np.cross(corner[:, 1] - corner[:, 0], corner[:, 2] - corner[:, 0])
    top = normals[:, 2] > 0.5  # the two triangles of the z = 1 face
    assert top.sum() == 2
    open_box = mesh_report(vertices, triangles[~top])
    assert not open_box.watertight and open_box.n_boundary_edges == 4 and open_box.n_non_manifold_edges == 0

    flipped = triangles.copy()
    flipped[0] = flipped[0, ::-1]
    one_flipped = mesh_report(vertices, flipped)
    assert one_flipped.watertight and not one_flipped.consistently_oriented

    fan = mesh_report(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1.0]]),
                      np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]]))  # three triangles on edge 0-1
    assert fan.n_non_manifold_edges == 1 and fan.n_boundary_edges == 6 and not fan.watertight


def test_trimming_that_would_open_the_mesh_is_refused_and_said():
    directions = _sphere_directions(12_000)
    capless = directions[directions[:, 2] < 0.8]  # the top cap was never scanned
    # At scale 1.1 (MeshLab's default) the bridged cap leaves the reconstruction cube and is cut open.
    settings = {"samples_per_node": CFG.samples_per_node, "point_weight": CFG.point_weight}
    cut = screened_poisson(RADIUS * capless, capless, depth=6, scale=1.1, **settings)
    assert not cut.report.watertight and cut.report.n_boundary_edges > 0
    assert "not watertight" in cut.note
    closed = screened_poisson(RADIUS * capless, capless, depth=6, scale=1.4, **settings)
    assert closed.report.watertight, closed.report
    cap, scanned = closed.vertices[:, 2] > 0.85 * RADIUS, closed.vertices[:, 2] < 0.7 * RADIUS
    assert closed.vertex_density[cap].max() < closed.vertex_density[scanned].min()  # the bridge is low-density

    refused = screened_poisson(RADIUS * capless, capless, depth=6, scale=1.4, trim_density_quantile=0.05, **settings)
    assert not refused.trimmed and refused.report.watertight
    np.testing.assert_array_equal(refused.vertices, closed.vertices)
    np.testing.assert_array_equal(refused.triangles, closed.triangles)
    assert "opens the mesh" in refused.note and "untrimmed" in refused.note

    opened = screened_poisson(RADIUS * capless, capless, depth=6, scale=1.4, trim_density_quantile=0.05,
                              keep_watertight=False, **settings)
    assert opened.trimmed and opened.n_trimmed_triangles > 0
    assert not opened.report.watertight and opened.report.n_boundary_edges > 0
    assert opened.report.n_triangles == closed.report.n_triangles - opened.n_trimmed_triangles


def test_trimming_a_whole_sparse_blob_keeps_the_mesh_closed():
    big, small = _sphere_directions(12_000), _sphere_directions(150)
    points = np.concatenate([RADIUS * big, 3.0 * small + [40.0, 0.0, 0.0]])  # a sparsely seen 3 mm ball
    normals = np.concatenate([big, small])
    full = screened_poisson(points, normals, depth=6, **POISSON)
    assert full.report.watertight
    in_blob = np.linalg.norm(full.vertices - [40.0, 0.0, 0.0], axis=1) < 6.0
    assert full.vertex_density[in_blob].max() < full.vertex_density[~in_blob].min()
    quantile = in_blob.sum() / (len(in_blob) - 1)  # the threshold falls on the big sphere's lowest density
    trimmed = screened_poisson(points, normals, depth=6, trim_density_quantile=quantile, **POISSON)
    assert trimmed.trimmed and trimmed.report.watertight
    assert "removes" in trimmed.note and "opens" not in trimmed.note
    assert trimmed.report.n_vertices == full.report.n_vertices - in_blob.sum()
    assert np.linalg.norm(trimmed.vertices, axis=1).max() < RADIUS + 0.1


@pytest.mark.parametrize("suffix", [".stl", ".ply"])
def test_written_mesh_reads_back(tmp_path, unit_box, suffix):
    vertices, triangles = unit_box
    path = tmp_path / f"box{suffix}"
    write_mesh(path, vertices * 25.0, triangles)
    back = o3d.io.read_triangle_mesh(str(path))
    assert len(back.triangles) == len(triangles)
    assert mesh_report(np.asarray(back.vertices), np.asarray(back.triangles)).volume_mm3 == pytest.approx(25.0**3)


def test_write_errors(tmp_path, unit_box):
    vertices, triangles = unit_box
    with pytest.raises(OSError, match="no_such_dir"):
        write_mesh(tmp_path / "no_such_dir" / "box.stl", vertices, triangles)
    with pytest.raises(ValueError, match=r"\.stl or \.ply"):
        write_mesh(tmp_path / "box.obj", vertices, triangles)
    with pytest.raises(ValueError, match="binary STL only"):
        write_mesh(tmp_path / "box.stl", vertices, triangles, binary=False)


def test_bad_arguments():
    p = np.zeros((10, 3))
    with pytest.raises(ValueError, match=r"normals must have one row per point \(10\)"):
        screened_poisson(p, np.ones((9, 3)), depth=6, **POISSON)
    with pytest.raises(ValueError, match="depth must be an integer"):
        screened_poisson(p, np.ones((10, 3)), depth=0, **POISSON)
    with pytest.raises(ValueError, match="trim_density_quantile"):
        screened_poisson(p, np.ones((10, 3)), depth=6, trim_density_quantile=1.0, **POISSON)
    with pytest.raises(ValueError, match="samples_per_node must be > 0"):
        screened_poisson(p, np.ones((10, 3)), depth=6, **{**POISSON, "samples_per_node": 0.0})
    with pytest.raises(ValueError, match="scale must be >= 1"):
        screened_poisson(p, np.ones((10, 3)), depth=6, **{**POISSON, "scale": 0.9})
    with pytest.raises(TypeError, match="scale"):  # the config's settings have no second default here
        screened_poisson(p, np.ones((10, 3)), depth=6, samples_per_node=1.5, point_weight=4.0)
    with pytest.raises(TypeError, match="threads"):  # MeshLab always runs on one thread (same bytes)
        screened_poisson(p, np.ones((10, 3)), depth=6, threads=2, **POISSON)
    with pytest.raises(ValueError, match="zero vectors"):
        screened_poisson(p, np.zeros((10, 3)), depth=6, **POISSON)
    with pytest.raises(ValueError, match="k must be an integer >= 3"):
        estimate_normals(p, p, k=2)
    with pytest.raises(ValueError, match="need at least k = 12 points"):
        estimate_normals(p, p, k=12)
    with pytest.raises(ValueError, match=r"sensor_positions_mm must have shape \(n, 3\)"):
        estimate_normals(p, np.zeros((10, 2)), k=3)
    with pytest.raises(ValueError, match="outside 0..2"):
        mesh_report(np.eye(3), np.array([[0, 1, 3]]))
    with pytest.raises(ValueError, match="integer vertex indices"):
        mesh_report(np.eye(3), np.array([[0.0, 1.0, 2.0]]))
    with pytest.raises(ValueError, match="vertices holds NaN"):
        mesh_report(np.full((3, 3), np.nan), np.array([[0, 1, 2]]))
