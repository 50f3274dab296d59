"""Boundary slivers repaired (tasks.sliver_repair): a known sliver made on a clean mesh is taken
out again, the solid staying closed and its volume kept, in milliseconds."""

from __future__ import annotations

import itertools
import os
import subprocess
import sys

import numpy as np
import pytest

from tasks import sliver_repair
from tasks.sliver_repair import repair_boundary_slivers
from tasks.volume_mesh import (VolumeMesh, boundary_faces, element_quality, face_nodes, orient_tetrahedra,
                               signed_volumes, solid_checks)


def kuhn_block(n: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """A cube of n^3 1 mm cells, each split into six tetrahedra along its main diagonal (smallest
    dihedral angle 45 deg, aspect ratio 1.39)."""
    index = np.arange((n + 1) ** 3).reshape(n + 1, n + 1, n + 1)
    points = np.stack(np.meshgrid(*[np.arange(n + 1.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    tets = []
    for cell in itertools.product(range(n), repeat=3):
        for order in itertools.permutations(range(3)):
            corner, path = np.array(cell), [index[cell]]
            for axis in order:
                corner = corner + np.eye(3, dtype=int)[axis]
                path.append(index[tuple(corner)])
            tets.append(path)
    return points, orient_tetrahedra(points, np.array(tets, np.int64))


def one_solid(points: np.ndarray, tets: np.ndarray) -> bool:
    element, face = boundary_faces(tets)
    mesh = VolumeMesh(points=points, tetrahedra=tets, boundary_element=element, boundary_face=face,
                      weld_zone_face=np.zeros(len(element), bool))
    checks = solid_checks(mesh, 64.0)
    return checks.components == 1 and checks.negative_or_flat == 0 and checks.open_boundary_edges == 0


def test_a_flat_element_over_two_surface_triangles_is_peeled_off():
    points, tets = kuhn_block()
    # two top triangles sharing a diagonal, the diagonal lowered 0.02 mm (a valley), a flat element over them
    faces = face_nodes(tets, *boundary_faces(tets))
    top = faces[np.all(points[faces][:, :, 2] == 4.0, axis=1)]
    by_edge: dict[tuple[int, int], list] = {}
    for tri in top.tolist():
        for u, v in ((0, 1), (1, 2), (2, 0)):
            by_edge.setdefault(tuple(sorted((tri[u], tri[v]))), []).append(tri)
    (a, c), (t1, t2) = next((e, f) for e, f in sorted(by_edge.items())
                            if len(f) == 2 and np.linalg.norm(points[e[0]] - points[e[1]]) > 1.2)
    b, d = (next(n for n in t if n not in (a, c)) for t in (t1, t2))
    points[[a, c], 2] -= 0.02
    capped = orient_tetrahedra(points, np.vstack([tets, [[a, b, c, d]]]))
    dihedral, aspect = element_quality(points, capped)
    assert dihedral.min() < 3 and aspect.max() > 20 and one_solid(points, capped)

    repaired = repair_boundary_slivers(points, capped)
    assert (repaired.peeled, repaired.collapsed, repaired.slid, repaired.left) == (1, 0, 0, 0)
    assert np.array_equal(np.sort(np.sort(repaired.tetrahedra, axis=1), axis=0), np.sort(np.sort(tets, axis=1), axis=0))
    assert np.array_equal(repaired.points, points)


def test_a_short_surface_edge_is_collapsed_keeping_the_solid_and_its_volume():
    points, tets = kuhn_block()
    moved = int(np.flatnonzero(np.all(points == [2, 2, 4], axis=1))[0])
    points[moved] = [2.99, 2.0, 4.0]  # 0.01 mm from its neighbour (3, 2, 4) along the top face
    dihedral, aspect = element_quality(points, tets)
    assert dihedral.min() < 1 and aspect.max() > 50 and one_solid(points, tets)

    repaired = repair_boundary_slivers(points, tets)
    assert repaired.collapsed == 1 and repaired.left == 0
    dihedral, aspect = element_quality(repaired.points, repaired.tetrahedra)
    assert dihedral.min() >= 10 and aspect.max() <= 10
    assert len(repaired.points) == len(points) - 1 and one_solid(repaired.points, repaired.tetrahedra)
    assert signed_volumes(repaired.points, repaired.tetrahedra).sum() == pytest.approx(64.0, abs=1e-9)
    # the same mesh, the same result
    again = repair_boundary_slivers(points, tets)
    assert np.array_equal(again.tetrahedra, repaired.tetrahedra) and np.array_equal(again.points, repaired.points)


def test_nodes_are_moved_to_mend_flat_elements_the_surface_ones_within_their_faces():
    points, tets = kuhn_block(2)
    node = int(np.flatnonzero(np.all(points == [1, 1, 2], axis=1))[0])
    points[node] += [0.85, 0.6, 0.0]  # along the top face, toward the far corner of its cell: flat elements, no short edge
    dihedral, aspect = element_quality(points, tets)
    assert dihedral.min() < 5 and aspect.max() > 40 and one_solid(points, tets)

    repaired = repair_boundary_slivers(points, tets)
    assert (repaired.peeled, repaired.collapsed, repaired.left) == (0, 0, 0) and repaired.slid >= 1
    assert np.array_equal(repaired.tetrahedra, tets)
    dihedral, aspect = element_quality(repaired.points, repaired.tetrahedra)
    assert dihedral.min() >= 10 and aspect.max() <= 10
    # the surface where it was: its nodes moved only within their faces (the box's), the one moved too
    assert np.array_equal(np.isin(repaired.points, [0.0, 2.0]), np.isin(points, [0.0, 2.0]))
    assert repaired.points[node, 2] == 2.0 and not np.array_equal(repaired.points[node], points[node])
    assert signed_volumes(repaired.points, tets).sum() == pytest.approx(8.0, abs=1e-12)


def test_a_node_on_a_sharp_edge_slides_along_it_and_a_corner_stays():
    # (the paper preset's slivers at a plate's rounded edge, where no inner node's place mends them)
    points, tets = kuhn_block(2)
    node = int(np.flatnonzero(np.all(points == [2, 1, 2], axis=1))[0])
    points[node, 1] += 0.9  # along the block's edge x = z = 2, 0.1 mm from the corner (2, 2, 2)
    before = points.copy()
    dihedral, _ = element_quality(points, tets)
    worst = int(np.argmin(dihedral))
    assert dihedral[worst] < 5 and node in tets[worst]
    mesh, surface = sliver_repair._Mesh(points, tets.copy(), (10.0, 10.0)), sliver_repair._Surface(points, tets)

    assert sliver_repair._try_slide(mesh, worst, surface)
    moved = np.flatnonzero(np.any(points != before, axis=1))
    assert moved.tolist() == [node]  # the corner, a node of the same element, stays where it is
    assert points[node, [0, 2]].tolist() == [2.0, 2.0] and abs(points[node, 1] - 1.0) < 0.05  # on the edge
    dihedral, aspect = element_quality(points, tets)
    assert dihedral.min() > 40 and aspect.max() < 1.5 and one_solid(points, tets)


def test_the_same_mesh_gives_the_same_bytes_with_any_number_of_threads():
    code = ("import hashlib, numpy as np; from tests.tasks.test_sliver_repair import kuhn_block;"
            "from tasks.sliver_repair import repair_boundary_slivers; p, t = kuhn_block(2);"
            "p[13] += [0.3, -0.2, 0.1]; p[14] += [0.85, 0.6, 0.0]; r = repair_boundary_slivers(p, t);"
            "print(r.slid, hashlib.sha256(r.points.tobytes() + r.tetrahedra.tobytes()).hexdigest())")
    answers = set()
    for threads in ("1", "4"):
        env = {**os.environ, "OMP_NUM_THREADS": threads, "OPENBLAS_NUM_THREADS": threads, "MKL_NUM_THREADS": threads}
        done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env)
        answers.add(done.stdout.strip())
    assert len(answers) == 1 and int(answers.pop().split()[0]) >= 1


def test_a_mesh_within_the_limits_is_left_as_it_is():
    points, tets = kuhn_block(2)
    repaired = repair_boundary_slivers(points, tets)
    assert (repaired.peeled, repaired.collapsed, repaired.slid, repaired.left) == (0, 0, 0, 0)
    assert np.array_equal(repaired.tetrahedra, tets) and np.array_equal(repaired.points, points)


@pytest.mark.parametrize("points, tets, message", [
    (np.zeros((4, 2)), np.array([[0, 1, 2, 3]]), r"points must be \(p, 3\)"),
    (np.zeros((4, 3)), np.array([[0, 1, 2]]), r"tetrahedra must be \(e, 4\)"),
    (np.zeros((4, 3)), np.array([[0, 1, 2, 4]]), r"numbers of the 4 points"),
])
def test_bad_input_is_refused_saying_what_is_wrong(points, tets, message):
    with pytest.raises(ValueError, match=message):
        repair_boundary_slivers(points, tets)
