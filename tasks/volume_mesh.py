"""The FE model: a tetrahedral volume mesh of the closed surface, graded toward the weld, made by
gmsh, with its element quality and the checks that it is one solid.

gmsh (``classifySurfaces`` + ``createGeometry``, as in its tutorial t13 for STL input) turns the
Poisson triangles into patches it can remesh, then meshes the surface and the volume with an
element size on the surface that is ``weld_size_mm`` within ``weld_zone_mm`` of the weld lines and
grows by ``growth`` per mm beyond, up to ``size_mm`` (gmsh's Distance and Threshold fields,
restricted to the surface; inside, the sizes grow from the surface's), the volume by gmsh's HXT
and its optimizer (Netgen's after it on request); the slivers left on the surface, out of the
optimisers' reach, repaired by local operations (``tasks.sliver_repair``). One thread and a fixed
seed: the same surface gives the same tetrahedra, in every process.

The files for FE programs (Abaqus ``.inp``, VTU) are written by ``data_catalog.volume_meshes``.
"""

from __future__ import annotations

import ctypes
import math
import os
import pickle
import resource
import signal
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from schemas.stage_documents import ElementQuality, QualityStatistics, SolidChecks
from tasks.arrays import distinct
from tasks.gmsh_volume import RESULT
from tasks.sliver_repair import MAX_ASPECT_RATIO, MIN_DIHEDRAL_DEG, repair_boundary_slivers
from tasks.weld_zone import weld_zone

__all__ = ["VolumeMesh", "VolumeMeshError", "VolumeMeshTimeout", "tetrahedralize", "triangle_pieces", "largest_piece", "boundary_faces", "element_quality", "solid_checks", "polyline_samples",
           "quality_summary", "signed_volumes", "orient_tetrahedra", "dies_with_parent", "run_limited", "face_nodes",
           "quadratic_tetrahedra", "element_face_nodes", "ONE_THREAD_ENV"]

# Abaqus C3D4 faces by the node each leaves out: S1 (1,2,3) leaves out node 4, S2 (1,4,2) node 3,
# S3 (2,4,3) node 1, S4 (3,4,1) node 2 (0-based below), each face's nodes here wound outward
# (counter-clockwise seen from outside a positively oriented element)
_FACES = ((0, 2, 1), (0, 1, 3), (1, 2, 3), (0, 3, 2))
_FACE_NUMBER = (1, 2, 3, 4)
# C3D10's edge nodes 5-10 (0-based 4-9) on the edges (1,2), (2,3), (3,1), (1,4), (2,4), (3,4): the
# same order as VTK's quadratic tetrahedron; and each face's three edge nodes, the face's corners' order
_EDGES = ((0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3))
_FACE_EDGES = ((6, 5, 4), (4, 8, 7), (5, 9, 8), (7, 9, 6))


class VolumeMeshError(ValueError):
    """The surface could not be meshed into one valid solid (the reason in the message)."""


class VolumeMeshTimeout(VolumeMeshError):
    """gmsh did not finish within the time it was given (its process is killed)."""


@dataclass(frozen=True)
class VolumeMesh:
    points: np.ndarray  # (p, 3) float64, mm, the surface mesh's frame
    tetrahedra: np.ndarray  # (e, 4) int64, positively oriented (Abaqus C3D4 / VTK order)
    boundary_element: np.ndarray  # (f,) int64: the tetrahedron each boundary face belongs to
    boundary_face: np.ndarray  # (f,) int64: which of its faces, Abaqus numbering 1-4
    weld_zone_face: np.ndarray  # (f,) bool: the face's centroid within the weld zone (tasks.weld_zone)
    surface_remeshed: bool = True  # False: gmsh could not reparametrise; the surface's own triangles kept
    surface_kept_because: str | None = None  # gmsh's message then
    slivers_peeled: int = 0  # flat elements on the surface removed (tasks.sliver_repair)
    short_edges_collapsed: int = 0  # the surface's short edges collapsed (tasks.sliver_repair)
    nodes_moved: int = 0  # nodes moved to mend poor elements: inside, or within a flat surface (tasks.sliver_repair)

    def boundary_triangles(self) -> np.ndarray:
        """(f, 3) int64, the boundary faces' nodes, counter-clockwise seen from outside."""
        return face_nodes(self.tetrahedra, self.boundary_element, self.boundary_face)

    def weld_zone_faces(self) -> dict[int, np.ndarray]:
        """Abaqus face number -> the elements (sorted, 0-based) whose face of that number is a
        boundary face in the weld zone: the element-face surface for sub-modelling."""
        zone = self.weld_zone_face
        chosen = {n: distinct(self.boundary_element[zone & (self.boundary_face == n)]) for n in _FACE_NUMBER}
        return {n: e for n, e in chosen.items() if len(e)}

    def weld_zone_nodes(self) -> np.ndarray:
        """The nodes (sorted, 0-based) of the weld zone's boundary faces."""
        return distinct(self.boundary_triangles()[self.weld_zone_face])


def polyline_samples(lines_mm: list[np.ndarray], step_mm: float) -> np.ndarray:
    """Points along each polyline (k, 3), at most ``step_mm`` apart, ends included: (n, 3)."""
    out = [np.zeros((0, 3))]
    for line in lines_mm:
        line = np.asarray(line, np.float64).reshape(-1, 3)
        for a, b in zip(line[:-1], line[1:]):
            n = int(np.ceil(np.linalg.norm(b - a) / step_mm)) + 1
            out.append(a + np.linspace(0.0, 1.0, n)[:, None] * (b - a))
        out.append(line[-1:])
    return np.vstack(out)


def tetrahedralize(vertices: np.ndarray, triangles: np.ndarray, *, weld_lines_mm: list[np.ndarray],
                   size_mm: float, weld_size_mm: float, weld_zone_mm: float, growth: float,
                   feature_angle_deg: float, optimize: bool, toe_size_mm: float, toe_zone_mm: float,
                   timeout_s: float, keep_surface_after_timeout: bool, toe_lines_mm: list[np.ndarray] = (), seed: int = 1,
                   min_dihedral_deg: float = MIN_DIHEDRAL_DEG, max_aspect_ratio: float = MAX_ASPECT_RATIO) -> VolumeMesh:
    """Tetrahedra filling the closed, outward-oriented triangle surface (vertices (v, 3) mm,
    triangles (t, 3)); sizes as in the module's description, and finer still toward the weld toes:
    ``toe_size_mm`` within ``toe_zone_mm`` of the ``toe_lines_mm`` (polylines (k, 3), mm, where the
    toes were measured), growing by ``growth`` per mm to the weld zone's size. Where gmsh cannot reparametrise the
    surface's patches (a patch of a topology it cannot flatten), the surface's own triangles are
    kept as the boundary and only the inside is meshed (``VolumeMesh.surface_remeshed`` False).
    Elements of smallest dihedral angle under ``min_dihedral_deg`` or aspect ratio over
    ``max_aspect_ratio`` that gmsh's optimiser leaves on the surface are repaired by
    ``tasks.sliver_repair`` (the surface moves by at most the sliver's thickness or the short
    edge's length).
    Raises VolumeMeshError when gmsh cannot mesh it either way (an open or self-intersecting
    surface) or made no tetrahedra; VolumeMeshTimeout when gmsh takes longer than ``timeout_s``
    (each try: a surface gmsh takes pathologically long over is not tried again), unless
    ``keep_surface_after_timeout``: then, as where it cannot reparametrise, once more with the
    surface's own triangles kept (gmsh's patch classification can stall on a surface: seen on a
    provisional mesh, ``flows.provisional``)."""
    vertices = np.ascontiguousarray(vertices, np.float64)
    triangles = np.ascontiguousarray(triangles, np.int64)
    if len(triangles) == 0:
        raise VolumeMeshError("the surface has no triangles")
    pieces, _ = triangle_pieces(triangles)
    if pieces > 1:
        raise VolumeMeshError(f"the surface is {pieces} separate pieces: more than one body (or a body with a "
                              "closed hollow inside), where the FE model is one solid")
    weld = polyline_samples(weld_lines_mm, step_mm=max(weld_size_mm, 0.05) / 2) if weld_lines_mm else None
    toes = None
    if len(toe_lines_mm) and toe_size_mm < weld_size_mm:
        toes = polyline_samples(toe_lines_mm, step_mm=max(toe_size_mm, 0.05) / 2)
    sizes = dict(size_mm=size_mm, weld_size_mm=weld_size_mm, weld_zone_mm=weld_zone_mm, growth=growth,
                 feature_angle_deg=feature_angle_deg, optimize=optimize, seed=seed, toes=toes,
                 toe_size_mm=toe_size_mm, toe_zone_mm=toe_zone_mm)
    remeshed, kept_because = True, None
    try:
        node_tags, coords, element_nodes = _gmsh_volume(vertices, triangles, weld, remesh=True, timeout_s=timeout_s,
                                                        **sizes)
    except VolumeMeshError as first:
        if isinstance(first, VolumeMeshTimeout) and not keep_surface_after_timeout:
            raise
        remeshed, kept_because = False, str(first)
        try:
            node_tags, coords, element_nodes = _gmsh_volume(vertices, triangles, weld, remesh=False,
                                                            timeout_s=timeout_s, **sizes)
        except VolumeMeshError as second:
            raise VolumeMeshError(f"{first}; keeping the surface's own triangles: {second}") from second
    if len(element_nodes) == 0:
        raise VolumeMeshError("gmsh made no tetrahedra: the surface does not enclose one volume (open, or "
                              "more than one body)")
    coords = np.asarray(coords, np.float64).reshape(-1, 3)
    tets_by_tag = np.asarray(element_nodes, np.int64).reshape(-1, 4)
    used = distinct(tets_by_tag)  # nodes no tetrahedron uses (gmsh's own) are left out
    index = np.full(int(np.max(node_tags)) + 1, -1, np.int64)
    index[np.asarray(node_tags, np.int64)] = np.arange(len(node_tags))
    keep = index[used]
    renumber = np.full(index.shape, -1, np.int64)
    renumber[used] = np.arange(len(used))
    points, tets = coords[keep], renumber[tets_by_tag]
    tets = orient_tetrahedra(points, tets)
    # the slivers on the surface gmsh's optimiser cannot reach (tasks.sliver_repair)
    repair = repair_boundary_slivers(points, tets, min_dihedral_deg=min_dihedral_deg, max_aspect_ratio=max_aspect_ratio)
    points, tets = repair.points, repair.tetrahedra
    element, face = boundary_faces(tets)
    faces = face_nodes(tets, element, face)
    in_zone = weld_zone(list(weld_lines_mm), weld_zone_mm).faces_in(points, faces)  # the one weld zone (tasks.weld_zone)
    return VolumeMesh(points=points, tetrahedra=tets, boundary_element=element, boundary_face=face,
                      weld_zone_face=in_zone, surface_remeshed=remeshed, surface_kept_because=kept_because,
                      slivers_peeled=repair.peeled,
                      short_edges_collapsed=repair.collapsed, nodes_moved=repair.slid)


def triangle_pieces(triangles: np.ndarray) -> tuple[int, np.ndarray]:
    """How many pieces the triangles make, joined where they share a vertex, and each triangle's
    piece (0 .. count-1, numbered in the order of their lowest vertex index)."""
    triangles = np.asarray(triangles, np.int64)
    if len(triangles) == 0:
        return 0, np.zeros(0, np.int64)
    used, local = np.unique(triangles, return_inverse=True)
    local = local.reshape(triangles.shape)
    rows = np.concatenate([local[:, 0], local[:, 1]])
    cols = np.concatenate([local[:, 1], local[:, 2]])
    graph = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(len(used), len(used)))
    count, label = connected_components(graph, directed=False)
    return int(count), label[local[:, 0]].astype(np.int64)


def largest_piece(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """The piece of the surface of the largest area (``triangle_pieces``), its vertices renumbered
    in their order, and how many pieces there were: for a surface cut from a box that also holds
    what is not the part (a clamp's edge makes pieces of its own), where the FE model is the part
    alone."""
    triangles = np.asarray(triangles, np.int64)
    count, of_triangle = triangle_pieces(triangles)
    if count <= 1:
        return vertices, triangles, count
    v = np.asarray(vertices, np.float64)
    a, b, c = v[triangles[:, 0]], v[triangles[:, 1]], v[triangles[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    biggest = int(np.argmax(np.bincount(of_triangle, weights=area, minlength=count)))  # the lowest label on a tie
    kept = triangles[of_triangle == biggest]
    used = np.zeros(len(v), bool)
    used[kept.ravel()] = True
    index = np.cumsum(used) - 1
    return vertices[used], index[kept], count


# gmsh carries its own OpenBLAS and OpenMP, sized at load from the environment (OPENBLAS_NUM_THREADS,
# OMP_NUM_THREADS) and out of threadpoolctl's reach: a Dask worker (which sets them to 1) and a
# 2-core process made node coordinates differing in the 10th digit. So gmsh runs in a child
# process of its own, always with one thread of each: the same surface, the same bytes, from any
# caller.
ONE_THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def dies_with_parent():
    """A ``preexec_fn`` for a child process the kernel kills (SIGKILL) when this process dies,
    however it dies (``prctl(PR_SET_PDEATHSIG)``)."""
    parent = os.getpid()

    def in_the_child() -> None:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG
        if os.getppid() != parent:  # the parent died before the line above
            os._exit(1)

    return in_the_child


# a child's time limit is CPU time, not the wall clock's: a stalled gmsh spins (its patch
# classification, 9 minutes on one provisional surface), while on a busy machine a child mostly
# waits (the demo's provisional remesh: ~35 s of CPU in 91 s of wall time beside one busy process;
# in CI, beside the suite's other worker, a 120 s wall-clock limit left that model unmade). A child
# that waits on nothing is still killed after WALL_PER_CPU times its limit.
WALL_PER_CPU = 4.0


def run_limited(args: list[str], *, timeout_s: float, **kwargs) -> subprocess.CompletedProcess:
    """``subprocess.run(args, **kwargs)`` in a child that dies with this process
    (``dies_with_parent``), one thread's worth of work held to ``timeout_s`` seconds of CPU time
    (``RLIMIT_CPU``, whole seconds, at least one; no core file) and to ``WALL_PER_CPU`` times
    ``timeout_s`` of wall time. Raises ``subprocess.TimeoutExpired`` past either (the child killed)."""
    cpu_s = max(1, math.ceil(timeout_s))
    deaths = dies_with_parent()

    def in_the_child() -> None:
        deaths()
        resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
        resource.setrlimit(resource.RLIMIT_CPU, (cpu_s, cpu_s + 2))  # SIGXCPU, then SIGKILL

    done = subprocess.run(args, preexec_fn=in_the_child, timeout=WALL_PER_CPU * timeout_s, **kwargs)
    if done.returncode == -signal.SIGXCPU:  # (the hard limit's SIGKILL only for a child that ignores SIGXCPU)
        raise subprocess.TimeoutExpired(args, timeout_s, output=done.stdout, stderr=done.stderr)
    return done


def run_gmsh_child(script: str, payload, *, timeout_s: float, failed: type[Exception], too_slow: Exception):
    """``tasks/<script>`` (a gmsh child: ``gmsh_volume.py``, ``gmsh_sections.py``) run by its path in
    a fresh process with one thread (``ONE_THREAD_ENV``), ``payload`` pickled on its stdin; returns
    what it answers after ``RESULT``. Run by path, not imported from the package: the child loads
    numpy and gmsh alone, not what ``tasks`` loads for every stage (pymeshlab, scipy: 1.2 s of a
    ~10 s child). Raises ``too_slow`` (its process killed) past ``timeout_s`` of CPU time
    (``run_limited``), ``failed(message)`` when it dies or says an error."""
    env = {**os.environ, **ONE_THREAD_ENV}
    try:
        done = run_limited([sys.executable, str(Path(__file__).with_name(script))], input=pickle.dumps(payload),
                           capture_output=True, env=env, timeout_s=timeout_s)
    except subprocess.TimeoutExpired:  # the child is killed
        raise too_slow from None
    if done.returncode != 0 or RESULT not in done.stdout:
        tail = done.stderr.decode("utf-8", "replace").strip().splitlines()[-1:] or ["no message"]
        raise failed(f"the gmsh process failed (exit {done.returncode}): {tail[0]}")
    kind, value = pickle.loads(done.stdout.rsplit(RESULT, 1)[1])
    if kind == "error":
        raise failed(value)
    return value


def _gmsh_volume(vertices, triangles, weld, *, timeout_s: float, **settings):
    """``tasks.gmsh_volume.gmsh_volume`` in a fresh child process with one thread (``run_gmsh_child``)."""
    return run_gmsh_child("gmsh_volume.py", (vertices, triangles, weld, settings), timeout_s=timeout_s,
                          failed=VolumeMeshError,
                          too_slow=VolumeMeshTimeout(f"gmsh did not finish within {timeout_s:g} s of CPU time "
                                                    "(volume.timeout_s)"))


def signed_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(e,) mm^3, positive for a positively oriented tetrahedron."""
    a, b, c, d = (points[tets[:, k]] for k in range(4))
    return np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) / 6.0


def orient_tetrahedra(points: np.ndarray, elements: np.ndarray) -> np.ndarray:
    """The elements (C3D4 or C3D10, Abaqus order) with the negatively oriented ones renumbered to
    positive (corners 1 and 2 swapped, and with them the edge nodes)."""
    elements = np.array(elements, copy=True)
    flip = signed_volumes(points, elements) < 0
    swap = [0, 2, 1, 3] if elements.shape[1] == 4 else [0, 2, 1, 3, 6, 5, 4, 7, 9, 8]
    elements[flip] = elements[flip][:, swap]
    return elements


def _face_keys(tets: np.ndarray) -> np.ndarray:
    faces = np.sort(tets[:, np.asarray(_FACES)].reshape(-1, 3), axis=1)
    return faces


def _same_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows of non-negative integers grouped: (the group of each row, the rows in each group);
    the groups numbered in no particular order. One int64 key a row where it fits (~10x faster
    than ``np.unique(axis=0)``), else rows compared as they are."""
    rows = np.asarray(rows, np.int64)
    base = int(rows.max()) + 1 if rows.size else 1
    if base ** rows.shape[1] < 2 ** 63:
        keys = np.zeros(len(rows), np.int64)
        for column in rows.T:
            keys = keys * base + column
        _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    else:
        _, inverse, counts = np.unique(rows, axis=0, return_inverse=True, return_counts=True)
    return inverse.ravel(), counts


def face_nodes(tets: np.ndarray, element: np.ndarray, face: np.ndarray) -> np.ndarray:
    """(f, 3) int64: the nodes of face ``face`` (Abaqus numbers 1-4) of each ``element``, wound
    counter-clockwise seen from outside a positively oriented tetrahedron."""
    return np.take_along_axis(np.asarray(tets)[element], np.asarray(_FACES)[np.asarray(face) - 1], axis=1)


def element_face_nodes(elements: np.ndarray, element: np.ndarray, face: np.ndarray) -> np.ndarray:
    """The nodes of face ``face`` (Abaqus numbers 1-4) of each ``element``: (f, 3) of C3D4 elements
    (e, 4), (f, 6) of C3D10 elements (e, 10): the corners as ``face_nodes``, then the edge nodes."""
    elements = np.asarray(elements)
    if elements.ndim != 2 or elements.shape[1] not in (4, 10):
        raise ValueError(f"elements must be (e, 4) or (e, 10) node numbers, got shape {elements.shape}")
    columns = np.asarray(_FACES) if elements.shape[1] == 4 else np.c_[np.asarray(_FACES), np.asarray(_FACE_EDGES)]
    return np.take_along_axis(elements[element], columns[np.asarray(face) - 1], axis=1)


def quadratic_tetrahedra(points: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """C3D10 elements of the C3D4 ``tets`` (e, 4), positively oriented, on ``points`` (p, 3) mm:
    (points (p + m, 3) mm, elements (e, 10)). The corners keep their numbers; the m edge nodes,
    one at the midpoint of each edge (straight-sided: the elements' shape is the linear ones'), follow
    in the order of their edges' sorted node pairs, so the same tetrahedra give the same model."""
    points = np.asarray(points, np.float64)
    tets = np.asarray(tets, np.int64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (p, 3) mm, got shape {points.shape}")
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise ValueError(f"tets must be (e, 4) node numbers (C3D4), got shape {tets.shape}")
    if len(tets) and (tets.min() < 0 or tets.max() >= len(points)):
        raise ValueError(f"tets name nodes outside 0..{len(points) - 1}")
    pairs = np.sort(tets[:, np.asarray(_EDGES)].reshape(-1, 2), axis=1)
    keys, edge_of = np.unique(pairs[:, 0] * len(points) + pairs[:, 1], return_inverse=True)  # sorted pairs
    first, second = np.divmod(keys, len(points))
    middle = (points[first] + points[second]) / 2
    return np.vstack([points, middle]), np.c_[tets, len(points) + edge_of.reshape(-1, 6)]


def boundary_faces(tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(element, Abaqus face number) of every face only one tetrahedron has, in element order."""
    inverse, counts = _same_rows(_face_keys(tets))
    once = np.flatnonzero(counts[inverse] == 1)
    return (once // 4).astype(np.int64), np.asarray(_FACE_NUMBER, np.int64)[once % 4]


def solid_checks(mesh: VolumeMesh, surface_volume_mm3: float) -> SolidChecks:
    """One solid? Connected through shared faces, every tetrahedron positive, a closed boundary
    (every boundary edge shared by two boundary faces), and its volume against the surface's."""
    tets = mesh.tetrahedra
    inverse, _ = _same_rows(_face_keys(tets))
    element = np.repeat(np.arange(len(tets)), 4)
    # element - face incidence: elements sharing a face are connected
    n_faces = int(inverse.max()) + 1
    incidence = coo_matrix((np.ones(len(element)), (element, inverse)), shape=(len(tets), n_faces)).tocsr()
    adjacency = incidence @ incidence.T
    n_components, _ = connected_components(adjacency, directed=False)
    volumes = signed_volumes(mesh.points, tets)
    boundary = mesh.boundary_triangles()
    edges = np.sort(np.concatenate([boundary[:, [0, 1]], boundary[:, [1, 2]], boundary[:, [2, 0]]]), axis=1)
    _, edge_counts = _same_rows(edges)
    volume = float(volumes.sum())
    return SolidChecks(tetrahedra=int(len(tets)), nodes=int(len(mesh.points)), boundary_faces=int(len(boundary)),
                       weld_zone_faces=int(np.count_nonzero(mesh.weld_zone_face)), components=int(n_components),
                       negative_or_flat=int(np.count_nonzero(volumes <= 0)),
                       open_boundary_edges=int(np.count_nonzero(edge_counts != 2)),
                       volume_mm3=volume, surface_volume_mm3=float(surface_volume_mm3),
                       volume_difference=volume / surface_volume_mm3 - 1.0 if surface_volume_mm3 else None)


def element_quality(points: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per tetrahedron: its smallest dihedral angle (degrees; 70.5 for the regular one) and its
    aspect ratio, circumradius / (3 x inradius) (1 for the regular one, growing as it degrades)."""
    p = points[tets]  # (e, 4, 3)
    normals = np.stack([np.cross(p[:, j] - p[:, i], p[:, k] - p[:, i]) for i, j, k in _FACES], axis=1)
    areas = np.linalg.norm(normals, axis=2) / 2
    unit = normals / np.maximum(2 * areas[..., None], 1e-300)
    dihedral = []
    for f, g in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)):  # each pair of faces shares one edge
        cos = -np.einsum("ij,ij->i", unit[:, f], unit[:, g])
        dihedral.append(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    min_dihedral = np.min(dihedral, axis=0)
    volume = np.abs(signed_volumes(points, tets))
    inradius = 3 * volume / np.maximum(areas.sum(axis=1), 1e-300)
    # circumradius: |a|^2 (b x c) + |b|^2 (c x a) + |c|^2 (a x b) over 12 V, with a, b, c from vertex 0
    a, b, c = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]
    num = ((a * a).sum(1)[:, None] * np.cross(b, c) + (b * b).sum(1)[:, None] * np.cross(c, a)
           + (c * c).sum(1)[:, None] * np.cross(a, b))
    circumradius = np.linalg.norm(num, axis=1) / np.maximum(12 * volume, 1e-300)
    return min_dihedral, circumradius / np.maximum(3 * inradius, 1e-300)


def quality_summary(min_dihedral_deg: np.ndarray, aspect_ratio: np.ndarray) -> ElementQuality:
    """The figures an FE analyst asks for: the worst element and the percentiles."""
    def stats(v: np.ndarray, worst: str) -> QualityStatistics:
        q = np.percentile(v, [1, 50, 99])
        return QualityStatistics(worst=round(float(v.min() if worst == "min" else v.max()), 4), p1=round(float(q[0]), 4),
                                 median=round(float(q[1]), 4), p99=round(float(q[2]), 4))

    return ElementQuality(min_dihedral_deg=stats(min_dihedral_deg, "min"), aspect_ratio=stats(aspect_ratio, "max"),
                          below_10_deg=int(np.count_nonzero(min_dihedral_deg < MIN_DIHEDRAL_DEG)))
