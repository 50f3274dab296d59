"""Surface: oriented normals, screened Poisson reconstruction (MeshLab, via pymeshlab), a
watertightness report computed on edges, and mesh export.

The finite-element model needs a closed mesh, so the report says plainly whether a mesh is
watertight (every undirected edge in exactly two triangles) and consistently oriented (no
directed edge twice); trimming low-density Poisson faces is refused when it would open the mesh,
unless the caller asks for the open mesh.

The same points, settings and code give the same bytes in any run, process, thread, thread count
or load (on one machine and library build): each normal is computed from its own neighbours alone,
whatever Open3D's thread count, and MeshLab's Poisson runs on one OpenMP thread (its solver sums
over threads in arrival order; see ``screened_poisson``).
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import threading
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import open3d as o3d
import pymeshlab
from scipy.spatial import cKDTree

from tasks.arrays import distinct
from tasks.checks import check_points

_MESHLAB = threading.Lock()

__all__ = ["MeshReport", "SurfaceResult", "estimate_normals", "flagged_vertices", "mesh_report", "screened_poisson",
           "simplify_surface", "write_mesh"]


@dataclass(frozen=True)
class MeshReport:
    """Counts and closure of a triangle mesh. ``watertight``: every undirected edge is shared by
    exactly two triangles (non-manifold vertices are not checked); ``consistently_oriented``: no
    directed edge occurs twice; ``volume_mm3`` signed (positive for a closed mesh whose triangles
    wind counter-clockwise seen from outside), meaningful only when watertight."""

    n_vertices: int
    n_triangles: int
    watertight: bool
    consistently_oriented: bool
    n_boundary_edges: int
    n_non_manifold_edges: int
    volume_mm3: float
    surface_area_mm2: float


@dataclass(frozen=True)
class SurfaceResult:
    """``vertices`` (v, 3) float64, mm; ``triangles`` (t, 3) int64 vertex indices;
    ``vertex_density`` (v,) float64, Poisson's sampling-density estimate at each vertex (MeshLab's
    vertex quality); ``report`` of the returned mesh; ``trimmed`` whether low-density faces were
    removed, ``n_trimmed_triangles`` how many; ``note`` what happened to a trim request (empty
    when nothing needs saying)."""

    vertices: np.ndarray
    triangles: np.ndarray
    vertex_density: np.ndarray
    report: MeshReport
    trimmed: bool
    n_trimmed_triangles: int
    note: str


def _check_mesh(vertices, triangles) -> tuple[np.ndarray, np.ndarray]:
    v = check_points("vertices", vertices)
    t = np.asarray(triangles)
    if t.ndim != 2 or t.shape[1] != 3:
        raise ValueError(f"triangles must have shape (t, 3), got {t.shape}")
    if t.size and not np.issubdtype(t.dtype, np.integer):
        raise ValueError(f"triangles must hold integer vertex indices, got dtype {t.dtype}")
    t = t.astype(np.int64)
    if t.size and (t.min() < 0 or t.max() >= len(v)):
        raise ValueError(f"triangles refer to vertices outside 0..{len(v) - 1}")
    return v, t


def estimate_normals(points_mm: np.ndarray, sensor_positions_mm: np.ndarray, *, k: int) -> np.ndarray:
    """Unit normals by PCA of each point's k nearest neighbours, each turned toward its sensor.

    points_mm : (n, 3) float, mm, n >= k.
    sensor_positions_mm : (n, 3) float, mm, the sensor position that saw each point.
    k : neighbours per point, including the point itself (Open3D's KNN search), >= 3.
    Returns (n, 3) float64 unit normals with dot(normal, sensor - point) >= 0.
    Each normal depends on its own neighbours only (Open3D sums no quantity across points), so
    the result is the same bytes for any number of threads (measured: OMP_NUM_THREADS 1-8, busy
    cores, worker threads and Dask worker processes).
    """
    points = check_points("points_mm", points_mm)
    sensors = check_points("sensor_positions_mm", sensor_positions_mm, len(points))
    if not isinstance(k, (int, np.integer)) or k < 3:
        raise ValueError(f"k must be an integer >= 3 (a plane needs three points), got {k}")
    if len(points) < k:
        raise ValueError(f"need at least k = {k} points, got {len(points)}")
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=int(k)))
    normals = np.asarray(cloud.normals).copy()
    away = np.einsum("ij,ij->i", normals, sensors - points) < 0
    normals[away] *= -1.0
    return normals


def mesh_report(vertices: np.ndarray, triangles: np.ndarray) -> MeshReport:
    """Closure, orientation, volume and area of a triangle mesh, from its edges (numpy only).

    vertices : (v, 3) float, mm.
    triangles : (t, 3) int, indices into vertices.
    The signed volume is taken about the vertex centroid (the same as about the origin for a
    closed mesh, and better conditioned).
    """
    v, t = _check_mesh(vertices, triangles)
    nv = max(len(v), 1)
    a, b = t[:, [0, 1, 2]].ravel(), t[:, [1, 2, 0]].ravel()
    directed = a * nv + b
    undirected = np.minimum(a, b) * nv + np.maximum(a, b)
    _, uses = np.unique(undirected, return_counts=True)
    consistent = len(distinct(directed)) == len(directed)
    if len(t):
        p0, p1, p2 = (v[t[:, i]] - v.mean(axis=0) for i in range(3))
        cross = np.cross(p1 - p0, p2 - p0)
        area = 0.5 * float(np.linalg.norm(cross, axis=1).sum())
        volume = float(np.einsum("ij,ij->i", p0, np.cross(p1, p2)).sum()) / 6.0
    else:
        area = volume = 0.0
    return MeshReport(n_vertices=len(v), n_triangles=len(t), watertight=bool(len(t) and np.all(uses == 2)),
                      consistently_oriented=bool(consistent), n_boundary_edges=int(np.count_nonzero(uses == 1)),
                      n_non_manifold_edges=int(np.count_nonzero(uses > 2)), volume_mm3=volume, surface_area_mm2=area)


def _drop_unused_vertices(vertices, triangles, *per_vertex):
    used = np.zeros(len(vertices), bool)
    used[triangles.ravel()] = True
    new_index = np.cumsum(used) - 1
    return (vertices[used], new_index[triangles], *(a[used] for a in per_vertex))


def _canonical_order(vertices, triangles, density):
    """Vertices sorted by (x, y, z), triangles rotated to start at their least index (winding kept)
    and sorted: the output order then follows from the geometry alone, not from MeshLab's traversal."""
    order = np.lexsort(vertices.T[::-1])
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order))
    t = rank[triangles]
    shift = np.argmin(t, axis=1)
    t = np.take_along_axis(t, (shift[:, None] + np.arange(3)) % 3, axis=1)
    t = t[np.lexsort(t.T[::-1])]
    return vertices[order], t, density[order]


@contextlib.contextmanager
def _one_openmp_thread():
    """Limit the calling thread's OpenMP parallel regions to one thread, in the libgomp that
    pymeshlab loaded (``omp_set_num_threads`` holds for the calling thread only, so other threads
    keep their setting); restored on exit. No-op where no libgomp is loaded (macOS, Windows)."""
    try:
        gomp = ctypes.CDLL("libgomp.so.1", mode=os.RTLD_NOLOAD)
    except (OSError, AttributeError):
        yield
        return
    before = gomp.omp_get_max_threads()
    gomp.omp_set_num_threads(1)
    try:
        yield
    finally:
        gomp.omp_set_num_threads(before)


def screened_poisson(points_mm: np.ndarray, normals: np.ndarray, *, depth: int, samples_per_node: float,
                     point_weight: float, scale: float, trim_density_quantile: float = 0.0,
                     keep_watertight: bool = True) -> SurfaceResult:
    """Screened Poisson surface (Kazhdan & Hoppe 2013) via MeshLab's filter
    (``generate_surface_reconstruction_screened_poisson``).

    Parameters
    ----------
    points_mm : (n, 3) float, mm, n >= 3.
    normals : (n, 3) float, outward normals of the points (only the direction matters).
    depth : octree depth, 1..16; the finest cell is about scale * (largest bounding-box edge) / 2**depth.
        Too few points per node (see samples_per_node) keeps the octree shallower than asked.
    trim_density_quantile : in [0, 1): remove the triangles touching a vertex whose density is
        below this quantile of the vertex densities (low density = far from the samples, e.g.
        where Poisson bridged a hole). 0 trims nothing.
    keep_watertight : when trimming would open a closed mesh, return the untrimmed mesh and say so
        in ``note``; when False, return the trimmed, open mesh (``report.watertight`` False).
        Removing triangles nearly always opens a mesh unless whole closed pieces go.
    samples_per_node : MeshLab ``samplespernode``, minimum samples per octree node (1-5 clean, 15-20 noisy).
    point_weight : MeshLab ``pointweight``, the screening weight of the samples (0 is plain Poisson).
    scale : MeshLab ``scale``, the reconstruction cube over the points' bounding cube. Where a side
        was never scanned the surface can bulge out of that cube and is cut open there (the report
        shows boundary edges); a larger scale (1.3-1.5) closes it, at a coarser finest cell.

    Deterministic: the same inputs give the same bytes in any run, process, thread, thread count
    or load. MeshLab (PoissonRecon 9) sums the solver's dot products and constraints with OpenMP
    reductions and atomics in thread-arrival order, so it runs with ``threads=1`` here and every
    other OpenMP region of the call is held to one thread as well (``OMP_NUM_THREADS`` has no
    effect). Measured on the ci sample (383 k points, depth 8): 2 threads give other bytes than 1
    (10-20 % of the vertices move by ~1e-11 mm), 3 or 4 threads other bytes on every run; on 2
    busy cores 2 threads took 43-77 s instead of 3.5 s (MeshLab's threads spin while they wait).
    The output is put in a canonical order (vertices by coordinates).
    """
    points = check_points("points_mm", points_mm)
    normal_array = check_points("normals", normals, len(points))
    if len(points) < 3:
        raise ValueError(f"need at least 3 points, got {len(points)}")
    if not isinstance(depth, (int, np.integer)) or not 1 <= depth <= 16:
        raise ValueError(f"depth must be an integer in 1..16, got {depth}")
    if not 0.0 <= trim_density_quantile < 1.0:
        raise ValueError(f"trim_density_quantile must be in [0, 1), got {trim_density_quantile}")
    if not samples_per_node > 0 or not point_weight >= 0:
        raise ValueError(f"samples_per_node must be > 0 and point_weight >= 0, got {samples_per_node}, {point_weight}")
    if not scale >= 1.0:
        raise ValueError(f"scale must be >= 1, got {scale}")
    if np.any(np.linalg.norm(normal_array, axis=1) == 0):
        raise ValueError("normals holds zero vectors")
    with _MESHLAB, _one_openmp_thread():  # pymeshlab is not thread-safe: two runs at once crash (SIGSEGV)
        ms = pymeshlab.MeshSet()
        ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.ascontiguousarray(points),
                                   v_normals_matrix=np.ascontiguousarray(normal_array)))
        ms.generate_surface_reconstruction_screened_poisson(
            depth=int(depth), samplespernode=float(samples_per_node), pointweight=float(point_weight),
            scale=float(scale), preclean=False, confidence=False, threads=1)
        mesh = ms.current_mesh()
        vertices = np.array(mesh.vertex_matrix(), dtype=np.float64)
        triangles = np.array(mesh.face_matrix(), dtype=np.int64)
        density = np.array(mesh.vertex_scalar_array(), dtype=np.float64)
        del mesh, ms
    vertices, triangles, density = _canonical_order(*_drop_unused_vertices(vertices, triangles, density))
    report = mesh_report(vertices, triangles)
    notes = [] if report.watertight else [
        (f"the Poisson mesh is not watertight ({report.n_boundary_edges} boundary, "
         f"{report.n_non_manifold_edges} non-manifold edges)")]
    result = SurfaceResult(vertices=vertices, triangles=triangles, vertex_density=density, report=report,
                           trimmed=False, n_trimmed_triangles=0, note="; ".join(notes))
    if trim_density_quantile == 0.0 or len(triangles) == 0:
        return result
    threshold = float(np.quantile(density, trim_density_quantile))
    keep = (density[triangles] >= threshold).all(axis=1)
    n_trimmed = int(np.count_nonzero(~keep))
    if n_trimmed == 0:
        return result
    cut_vertices, cut_triangles, cut_density = _drop_unused_vertices(vertices, triangles[keep], density)
    cut_report = mesh_report(cut_vertices, cut_triangles)
    trim = (f"trimming below the {trim_density_quantile:g} density quantile ({threshold:.4g}) "
            f"removes {n_trimmed} triangles")
    if report.watertight and not cut_report.watertight:
        trim += f" and opens the mesh ({cut_report.n_boundary_edges} boundary edges)"
        if keep_watertight:
            return replace(result, note="; ".join([*notes, trim + ": returned the untrimmed, closed mesh"]))
        trim += ": returned the open, trimmed mesh"
    return SurfaceResult(vertices=cut_vertices, triangles=cut_triangles, vertex_density=cut_density, report=cut_report,
                         trimmed=True, n_trimmed_triangles=n_trimmed, note="; ".join([*notes, trim]))


def simplify_surface(vertices: np.ndarray, triangles: np.ndarray, *, max_triangles: int) -> tuple[np.ndarray, np.ndarray]:
    """The closed surface with at most ``max_triangles`` triangles: MeshLab's quadric edge
    collapse (Garland & Heckbert), topology and normals kept, planar quadrics so flat faces go
    first and bends keep their triangles; unchanged when it has no more. One thread, outputs in
    canonical order: the same surface gives the same bytes."""
    if len(triangles) <= max_triangles:
        return vertices, triangles
    with _MESHLAB, _one_openmp_thread():
        ms = pymeshlab.MeshSet()
        ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.ascontiguousarray(vertices, np.float64),
                                   face_matrix=np.ascontiguousarray(triangles, np.int32)))
        ms.meshing_decimation_quadric_edge_collapse(targetfacenum=int(max_triangles), qualitythr=0.5,
                                                    preserveboundary=True, preservenormal=True, preservetopology=True,
                                                    planarquadric=True, optimalplacement=True, autoclean=True)
        mesh = ms.current_mesh()
        out_vertices = np.array(mesh.vertex_matrix(), dtype=np.float64)
        out_triangles = np.array(mesh.face_matrix(), dtype=np.int64)
        del mesh, ms
    out_vertices, out_triangles, _ = _canonical_order(*_drop_unused_vertices(out_vertices, out_triangles,
                                                                             np.zeros(len(out_vertices))))
    return out_vertices, out_triangles


def flagged_vertices(vertices: np.ndarray, points_mm: np.ndarray, flags: np.ndarray) -> np.ndarray:
    """(v,) bool: the flag of the point nearest to each vertex (e.g. which resolution zone of the
    merged cloud a mesh vertex lies in). vertices (v, 3), points_mm (n, 3) mm, flags (n,) bool."""
    v = check_points("vertices", vertices)
    points = check_points("points_mm", points_mm)
    flags = np.asarray(flags, dtype=bool)
    if flags.shape != (len(points),):
        raise ValueError(f"flags must have one entry per point ({len(points)}), got shape {flags.shape}")
    if len(points) == 0:
        raise ValueError("points_mm is empty")
    _, nearest = cKDTree(points).query(v, k=1, workers=1)
    return flags[nearest]


def write_mesh(path: str | os.PathLike, vertices: np.ndarray, triangles: np.ndarray, *, binary: bool = True) -> None:
    """Write a triangle mesh as .stl (binary only; per-triangle normals computed) or .ply, via Open3D.

    vertices : (v, 3) float, mm (STL stores them as float32).
    triangles : (t, 3) int, indices into vertices.
    Raises ValueError for an unknown suffix or ASCII STL (Open3D 0.20 cannot write it), and
    OSError naming the path when the file cannot be written.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".stl", ".ply"):
        raise ValueError(f"mesh path must end in .stl or .ply, got {path}")
    if suffix == ".stl" and not binary:
        raise ValueError(f"Open3D writes binary STL only; use binary=True or a .ply path for {path}")
    v, t = _check_mesh(vertices, triangles)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(t.astype(np.int32)))
    if suffix == ".stl":
        mesh.compute_triangle_normals()
    try:
        ok = o3d.io.write_triangle_mesh(str(path), mesh, write_ascii=not binary)
    except RuntimeError as error:
        raise OSError(f"could not write mesh to {path}: {error}") from error
    if not ok:
        raise OSError(f"could not write mesh to {path}")
