"""The FE volume mesh (tasks.volume_mesh): gmsh's tetrahedra of a closed surface, one solid of its
volume, graded toward the weld, written for Abaqus and VTK and read back by meshio."""

from __future__ import annotations

import hashlib
import subprocess
import sys

import meshio
import numpy as np
import pytest

from tasks.mesh import mesh_report
from data_catalog.volume_meshes import write_abaqus, write_vtu
from tasks.volume_mesh import (VolumeMesh, VolumeMeshError, element_face_nodes, element_quality, orient_tetrahedra,
                               polyline_samples, quadratic_tetrahedra, quality_summary, signed_volumes, solid_checks,
                               tetrahedralize)

# a plate 40 x 20 x 6 mm with a weld line across its top face at x = 0
BOX = (40.0, 20.0, 6.0)
WELD = [np.array([[0.0, -10.0, 3.0], [0.0, 10.0, 3.0]])]
SIZES = dict(size_mm=4.0, weld_size_mm=0.8, weld_zone_mm=2.0, growth=0.5,
             feature_angle_deg=40.0, optimize=True, toe_size_mm=0.8, toe_zone_mm=0.0,  # toes: no finer (off)
             timeout_s=600.0, keep_surface_after_timeout=False)


def box_surface(size=BOX, n=8, offset=(0.0, 0.0, 0.0)):
    """A closed, outward-oriented triangulated box, each face split into n x n squares."""
    vertices, triangles = [], []
    half = np.asarray(size) / 2
    for axis in range(3):
        for sign in (-1.0, 1.0):
            u, v = [a for a in range(3) if a != axis]
            s, t = np.meshgrid(np.linspace(-1, 1, n + 1), np.linspace(-1, 1, n + 1), indexing="ij")
            p = np.zeros((n + 1, n + 1, 3))
            p[..., axis], p[..., u], p[..., v] = sign * half[axis], s * half[u], t * half[v]
            base = sum(len(x) for x in vertices)
            vertices.append(p.reshape(-1, 3))
            idx = base + np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
            a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
            quads = np.stack([a, b, c, d], -1).reshape(-1, 4)
            tri = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
            # (u, v, axis) right-handed for axis 0 and 2 with this (u, v) order, left-handed for axis 1
            outward = sign * (1 if axis != 1 else -1)
            triangles.append(tri if outward > 0 else tri[:, [0, 2, 1]])
    vertices = np.vstack(vertices) + np.asarray(offset)
    triangles = np.vstack(triangles)
    # weld the faces' shared edge vertices into one
    unique, inverse = np.unique(np.round(vertices, 9), axis=0, return_inverse=True)
    return unique, inverse.ravel()[triangles]


@pytest.fixture(scope="module")
def plate():
    vertices, triangles = box_surface()
    assert mesh_report(vertices, triangles).watertight
    return vertices, triangles, tetrahedralize(vertices, triangles, weld_lines_mm=WELD, **SIZES)


def test_the_box_is_one_positive_solid_of_its_volume(plate):
    vertices, triangles, solid = plate
    checks = solid_checks(solid, mesh_report(vertices, triangles).volume_mm3)
    assert checks.components == 1 and checks.negative_or_flat == 0 and checks.open_boundary_edges == 0
    assert checks.surface_volume_mm3 == pytest.approx(np.prod(BOX), rel=1e-9)
    assert abs(checks.volume_difference) < 1e-6  # flat faces: the remeshed surface is the box itself
    assert np.all(signed_volumes(solid.points, solid.tetrahedra) > 0)
    # the boundary is the box's surface, wound outward: its signed volume is the solid's
    b = solid.boundary_triangles()
    p = solid.points
    assert np.einsum("ij,ij->i", p[b[:, 0]], np.cross(p[b[:, 1]], p[b[:, 2]])).sum() / 6 == pytest.approx(np.prod(BOX))


def test_elements_are_finer_at_the_weld_and_the_weld_zone_is_marked(plate):
    _, _, solid = plate
    # the surface's triangles: weld_size_mm at the weld line, growing away from it
    b = solid.points[solid.boundary_triangles()]
    edges = np.linalg.norm(b - np.roll(b, 1, axis=1), axis=2).mean(axis=1)
    centre = b.mean(axis=1)
    near = (np.abs(centre[:, 0]) < 1.5) & (centre[:, 2] > 2.9)
    far = np.abs(centre[:, 0]) > 15
    assert near.any() and far.any()
    assert np.median(edges[near]) < 1.2 * SIZES["weld_size_mm"]
    assert np.median(edges[far]) > 2.5 * np.median(edges[near])
    faces = solid.points[solid.boundary_triangles()].mean(axis=1)
    zone = solid.weld_zone_face
    assert zone.any() and not zone.all()
    assert np.all(np.abs(faces[zone, 0]) <= SIZES["weld_zone_mm"] + 1e-9)
    assert np.all(faces[zone, 2] > 3.0 - SIZES["weld_zone_mm"] - 1e-9)
    outside = (np.abs(faces[:, 0]) > SIZES["weld_zone_mm"] + 0.5)
    assert not np.any(zone & outside)


def test_elements_are_finer_still_at_the_measured_toes(plate):
    vertices, triangles, solid = plate
    toes = [np.array([[x, -10.0, 3.0], [x, 10.0, 3.0]]) for x in (-1.5, 1.5)]  # two toes beside the weld line
    refined = tetrahedralize(vertices, triangles, weld_lines_mm=WELD, toe_lines_mm=toes,
                             **{**SIZES, "toe_size_mm": 0.3, "toe_zone_mm": 0.3})
    assert len(refined.tetrahedra) > len(solid.tetrahedra)

    def edges_near(s, x0):
        b = s.points[s.boundary_triangles()]
        edges = np.linalg.norm(b - np.roll(b, 1, axis=1), axis=2).mean(axis=1)
        centre = b.mean(axis=1)
        return edges[(np.abs(centre[:, 0] - x0) < 0.3) & (centre[:, 2] > 2.9)]

    for x0 in (-1.5, 1.5):
        assert np.median(edges_near(refined, x0)) < 0.45 < 0.6 < np.median(edges_near(solid, x0))
    # a toe size no finer than the weld's changes nothing
    same = tetrahedralize(vertices, triangles, weld_lines_mm=WELD, toe_lines_mm=toes, **{**SIZES, "toe_zone_mm": 1.0})
    assert np.array_equal(same.tetrahedra, solid.tetrahedra) and np.array_equal(same.points, solid.points)


def test_the_same_surface_gives_the_same_tetrahedra_in_another_process(plate):
    _, _, solid = plate
    here = hashlib.sha256(solid.points.tobytes() + solid.tetrahedra.tobytes()).hexdigest()
    code = ("import hashlib, numpy as np; from tests.tasks.test_volume_mesh import box_surface, WELD, SIZES;"
            "from tasks.volume_mesh import tetrahedralize; v, t = box_surface();"
            "s = tetrahedralize(v, t, weld_lines_mm=WELD, **SIZES);"
            "print(hashlib.sha256(s.points.tobytes() + s.tetrahedra.tobytes()).hexdigest())")
    there = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert there == here


def test_abaqus_and_vtu_read_back_with_meshio(plate, tmp_path):
    _, _, solid = plate
    dihedral, aspect = element_quality(solid.points, solid.tetrahedra)
    write_abaqus(tmp_path / "model.inp", solid.points, solid.tetrahedra, zone_faces=solid.weld_zone_faces(),
                 zone_nodes=solid.weld_zone_nodes())
    write_vtu(tmp_path / "model.vtu", solid.points, solid.tetrahedra,
              {"min_dihedral_deg": dihedral.astype(np.float32), "aspect_ratio": aspect.astype(np.float32)})
    inp = meshio.read(tmp_path / "model.inp")
    assert np.array_equal(inp.cells_dict["tetra"], solid.tetrahedra)
    assert np.allclose(inp.points, solid.points, rtol=0, atol=1e-6)
    zone_nodes = np.unique(solid.boundary_triangles()[solid.weld_zone_face])
    assert np.array_equal(np.sort(inp.point_sets["WELD_ZONE_NODES"]), zone_nodes)
    faces = {int(k[-1]): v[0] for k, v in inp.cell_sets.items() if k.startswith("WELD_ZONE_S")}
    expected = {n: np.unique(solid.boundary_element[solid.weld_zone_face & (solid.boundary_face == n)]) for n in range(1, 5)}
    assert faces and all(np.array_equal(np.sort(faces[n]), expected[n]) for n in faces)
    text = (tmp_path / "model.inp").read_text()
    assert text.count("*ELEMENT, TYPE=C3D4\n") == 1  # volume.element_order 1
    assert "*SURFACE, TYPE=ELEMENT, NAME=WELD_ZONE_SURFACE" in text
    assert all(f"WELD_ZONE_S{n}, S{n}" in text for n in faces)
    vtu = meshio.read(tmp_path / "model.vtu")
    assert np.array_equal(vtu.cells_dict["tetra"], solid.tetrahedra)
    assert np.allclose(vtu.cell_data["min_dihedral_deg"][0], dihedral, atol=1e-4)
    assert np.allclose(vtu.cell_data["aspect_ratio"][0], aspect, rtol=1e-6)


def test_abaqus_faces_leave_out_the_node_their_number_says():
    # one positive tetrahedron: each face's nodes wound outward (their normal away from the left-out node)
    points = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    tet = np.array([[0, 1, 2, 3]])
    solid = VolumeMesh(points=points, tetrahedra=tet, boundary_element=np.zeros(4, np.int64),
                       boundary_face=np.arange(1, 5), weld_zone_face=np.zeros(4, bool))
    for face in solid.boundary_triangles():
        left_out = ({0, 1, 2, 3} - set(face.tolist())).pop()
        a, b, c = points[face]
        assert np.dot(np.cross(b - a, c - a), a - points[left_out]) > 0
    assert sorted(map(tuple, map(sorted, solid.boundary_triangles().tolist()))) == [(0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3)]


def test_quality_of_the_regular_tetrahedron_and_a_sliver():
    regular = np.array([[1.0, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]])
    sliver = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.02]])
    dihedral, aspect = element_quality(np.vstack([regular, sliver]), np.array([[0, 1, 2, 3], [4, 5, 6, 7]]))
    assert dihedral[0] == pytest.approx(np.degrees(np.arccos(1 / 3)), abs=1e-9) and aspect[0] == pytest.approx(1.0)
    assert dihedral[1] < 3 and aspect[1] > 10
    summary = quality_summary(dihedral, aspect)
    assert summary.min_dihedral_deg.worst == pytest.approx(dihedral[1], abs=1e-4)
    assert summary.below_10_deg == 1


def test_solid_checks_see_two_bodies_and_a_flipped_element():
    one = tetrahedralize(*box_surface((10, 10, 10), n=2), weld_lines_mm=[], **{**SIZES, "size_mm": 5.0})
    n = len(one.points)
    two = VolumeMesh(points=np.vstack([one.points, one.points + [30.0, 0, 0]]),
                     tetrahedra=np.vstack([one.tetrahedra, one.tetrahedra + n]),
                     boundary_element=np.concatenate([one.boundary_element, one.boundary_element + len(one.tetrahedra)]),
                     boundary_face=np.tile(one.boundary_face, 2), weld_zone_face=np.tile(one.weld_zone_face, 2))
    checks = solid_checks(two, 2000.0)
    assert checks.components == 2 and checks.negative_or_flat == 0
    flipped = VolumeMesh(points=two.points, tetrahedra=two.tetrahedra[:, [0, 2, 1, 3]],
                         boundary_element=two.boundary_element, boundary_face=two.boundary_face,
                         weld_zone_face=two.weld_zone_face)
    assert solid_checks(flipped, 2000.0).negative_or_flat == len(two.tetrahedra)


def test_an_open_surface_is_refused():
    vertices, triangles = box_surface((10, 10, 10), n=2)
    top = vertices[triangles].mean(axis=1)[:, 2] > 4.9
    with pytest.raises(VolumeMeshError, match="gmsh|no tetrahedra|enclose"):
        tetrahedralize(vertices, triangles[~top], weld_lines_mm=[], **SIZES)
    a, b = box_surface((10, 10, 10), n=2), box_surface((10, 10, 10), n=2, offset=(30, 0, 0))
    with pytest.raises(VolumeMeshError, match="more than one body"):
        tetrahedralize(np.vstack([a[0], b[0]]), np.vstack([a[1], b[1] + len(a[0])]), weld_lines_mm=[], **SIZES)
    with pytest.raises(VolumeMeshError, match="no triangles"):
        tetrahedralize(vertices, triangles[:0], weld_lines_mm=[], **SIZES)


def test_gmsh_taking_longer_than_its_time_is_given_up_and_its_process_killed():
    """A surface gmsh stalls on (seen: a run whose normals a code edit had spoiled meshed for 15
    minutes) is given up after ``timeout_s`` (subprocess.run kills the child), with no second try."""
    from tasks.volume_mesh import VolumeMeshTimeout

    vertices, triangles = box_surface((10, 10, 10), n=2)
    with pytest.raises(VolumeMeshTimeout, match=r"gmsh did not finish within 0.01 s of CPU time \(volume.timeout_s\)"):
        tetrahedralize(vertices, triangles, weld_lines_mm=[], **{**SIZES, "timeout_s": 0.01})


def test_a_childs_limit_is_cpu_time_not_the_wall_clocks():
    """``run_limited``: a child spinning is killed once it has used its CPU seconds (gmsh's stalls
    spin); a child that waits (as a remesh does on a machine busy with other work) is not, until
    ``WALL_PER_CPU`` times as long has passed."""
    import subprocess
    import sys

    from tasks.volume_mesh import WALL_PER_CPU, run_limited

    spin = [sys.executable, "-c", "while True: pass"]
    with pytest.raises(subprocess.TimeoutExpired):
        run_limited(spin, timeout_s=1.0, capture_output=True)
    waits = run_limited([sys.executable, "-c", "import time; time.sleep(2.0); print('done')"], timeout_s=1.0,
                        capture_output=True, text=True)
    assert waits.returncode == 0 and waits.stdout == "done\n"  # 2 s of wall time, under a second of CPU
    assert WALL_PER_CPU * 1.0 > 2.0
    with pytest.raises(subprocess.TimeoutExpired):  # waiting past WALL_PER_CPU times the limit
        run_limited([sys.executable, "-c", "import time; time.sleep(60)"], timeout_s=0.25, capture_output=True)


def test_a_stalled_remesh_keeps_the_surface_when_asked(monkeypatch):
    """``keep_surface_after_timeout`` (the provisional FE model's): where the remeshing try ran out of
    its time (gmsh's patch classification stalled on a provisional surface for 9 minutes), the
    surface's own triangles are kept and the inside meshed, by the real gmsh; the stall is the
    one thing stood in for."""
    import tasks.volume_mesh as vm

    real = vm._gmsh_volume

    def stalling(vertices, triangles, weld, *, remesh, timeout_s, **sizes):
        if remesh:
            raise vm.VolumeMeshTimeout(f"gmsh did not finish within {timeout_s:g} s of CPU time (volume.timeout_s)")
        return real(vertices, triangles, weld, remesh=remesh, timeout_s=timeout_s, **sizes)

    monkeypatch.setattr(vm, "_gmsh_volume", stalling)
    vertices, triangles = box_surface((10, 10, 10), n=4)
    solid = tetrahedralize(vertices, triangles, weld_lines_mm=[], **{**SIZES, "keep_surface_after_timeout": True})
    assert not solid.surface_remeshed and "within 600 s" in solid.surface_kept_because
    p = solid.points[solid.tetrahedra]
    volume = np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0])).sum() / 6
    assert volume == pytest.approx(1000.0, rel=1e-9)  # the box, 10 mm a side, filled
    with pytest.raises(vm.VolumeMeshTimeout, match="within 600 s"):  # not asked: given up, as before
        tetrahedralize(vertices, triangles, weld_lines_mm=[], **SIZES)


def test_polyline_samples_keep_the_step_and_the_ends():
    line = np.array([[0.0, 0, 0], [10, 0, 0], [10, 5, 0]])
    samples = polyline_samples([line], step_mm=0.7)
    assert np.allclose(samples[0], line[0]) and np.allclose(samples[-1], line[-1])
    gaps = np.linalg.norm(np.diff(samples, axis=0), axis=1)
    assert gaps.max() <= 0.7 + 1e-12


def test_a_large_surface_is_simplified_first_keeping_its_volume_and_closure():
    import open3d as o3d

    from tasks.mesh import simplify_surface

    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=10.0, resolution=80)
    vertices, triangles = np.asarray(sphere.vertices), np.asarray(sphere.triangles)
    before = mesh_report(vertices, triangles)
    v, t = simplify_surface(vertices, triangles, max_triangles=4000)
    after = mesh_report(v, t)
    assert len(triangles) > 12_000 and 3900 <= len(t) <= 4000
    assert after.watertight and after.consistently_oriented
    assert abs(after.volume_mm3 / before.volume_mm3 - 1) < 0.002
    again = simplify_surface(vertices, triangles, max_triangles=4000)
    assert np.array_equal(again[0], v) and np.array_equal(again[1], t)  # the same bytes
    same = simplify_surface(vertices, triangles, max_triangles=len(triangles))
    assert same[0] is vertices and same[1] is triangles  # nothing to do: untouched


def test_a_surface_gmsh_cannot_reparametrise_keeps_its_own_triangles(monkeypatch):
    """The fallback: where remeshing fails, the inside is meshed on the surface's own triangles."""
    import tasks.volume_mesh as vm

    real = vm._gmsh_volume

    def no_remesh(*args, remesh, **kwargs):
        if remesh:
            raise VolumeMeshError("gmsh could not mesh the surface's volume: Wrong topology of boundary mesh")
        return real(*args, remesh=remesh, **kwargs)

    monkeypatch.setattr(vm, "_gmsh_volume", no_remesh)
    vertices, triangles = box_surface()
    solid = tetrahedralize(vertices, triangles, weld_lines_mm=WELD, **SIZES)
    assert not solid.surface_remeshed and "Wrong topology of boundary mesh" in solid.surface_kept_because
    checks = solid_checks(solid, mesh_report(vertices, triangles).volume_mm3)
    assert checks.components == 1 and checks.negative_or_flat == 0 and abs(checks.volume_difference) < 1e-9
    # the boundary is the input surface's triangles, less those the sliver repair merged (short
    # edges collapsed along the box's faces): every boundary node on the box's faces
    assert checks.boundary_faces <= len(triangles)
    on_face = np.isclose(np.abs(solid.points[np.unique(solid.boundary_triangles())]), np.asarray(BOX) / 2).any(axis=1)
    assert on_face.all()


@pytest.mark.parametrize("high", [50, 2 ** 40], ids=["one-key-a-row", "rows-as-they-are"])
def test_faces_and_edges_are_grouped_as_numpy_groups_equal_rows(high):
    from tasks.volume_mesh import _same_rows

    rng = np.random.default_rng(5)
    rows = rng.integers(0, high, (2000, 3))
    rows[1000:] = rows[rng.integers(0, 1000, 1000)]  # each repeated a few times
    inverse, counts = _same_rows(rows)
    _, expected_inverse, expected_counts = np.unique(rows, axis=0, return_inverse=True, return_counts=True)
    pairs = set(zip(inverse.tolist(), expected_inverse.ravel().tolist()))
    assert len(pairs) == len(counts) == len(expected_counts) < 2000  # the same partition of the rows
    assert np.array_equal(counts[inverse], expected_counts[expected_inverse.ravel()])


def test_quadratic_tetrahedra_put_one_shared_node_at_each_edge_midpoint(plate):
    _, _, solid = plate
    points, elements = quadratic_tetrahedra(solid.points, solid.tetrahedra)
    assert elements.shape == (len(solid.tetrahedra), 10)
    assert np.array_equal(elements[:, :4], solid.tetrahedra) and np.array_equal(points[:len(solid.points)], solid.points)
    # Abaqus C3D10 (= VTK tetra10): nodes 5-10 on the edges 1-2, 2-3, 3-1, 1-4, 2-4, 3-4
    for k, (i, j) in enumerate(((0, 1), (1, 2), (2, 0), (0, 3), (1, 3), (2, 3))):
        assert np.allclose(points[elements[:, 4 + k]], (points[elements[:, i]] + points[elements[:, j]]) / 2, rtol=0, atol=1e-12)
    # one node an edge, shared by the elements around it: nodes = corners + edges (Euler: V - E + F - T = 1)
    edges = len(points) - len(solid.points)
    faces = (4 * len(solid.tetrahedra) + len(solid.boundary_element)) // 2
    assert len(solid.points) - edges + faces - len(solid.tetrahedra) == 1
    # orientation kept (the edge nodes follow the corners when an element is renumbered)
    assert np.array_equal(orient_tetrahedra(points, elements), elements)
    # each boundary face's six nodes: its corners and the midpoints of its three edges, in order
    six = element_face_nodes(elements, solid.boundary_element, solid.boundary_face)
    assert np.array_equal(six[:, :3], solid.boundary_triangles())
    for k in range(3):
        assert np.allclose(points[six[:, 3 + k]], (points[six[:, k]] + points[six[:, (k + 1) % 3]]) / 2, atol=1e-12)


def test_quadratic_tetrahedra_refuse_bad_input():
    with pytest.raises(ValueError, match=r"tets must be \(e, 4\)"):
        quadratic_tetrahedra(np.zeros((10, 3)), np.zeros((1, 10), np.int64))
    with pytest.raises(ValueError, match=r"points must be \(p, 3\)"):
        quadratic_tetrahedra(np.zeros((4, 2)), np.array([[0, 1, 2, 3]]))
    with pytest.raises(ValueError, match="outside 0..3"):
        quadratic_tetrahedra(np.zeros((4, 3)), np.array([[0, 1, 2, 4]]))
    with pytest.raises(ValueError, match=r"\(e, 4\) or \(e, 10\)"):
        element_face_nodes(np.zeros((1, 8), np.int64), np.array([0]), np.array([1]))


def test_a_c3d10_model_reads_back_as_c3d10_with_its_edge_nodes(plate, tmp_path):
    _, _, solid = plate
    points, elements = quadratic_tetrahedra(solid.points, solid.tetrahedra)
    zone = solid.weld_zone_face
    zone_nodes = np.unique(element_face_nodes(elements, solid.boundary_element[zone], solid.boundary_face[zone]))
    write_abaqus(tmp_path / "model.inp", points, elements, zone_faces=solid.weld_zone_faces(), zone_nodes=zone_nodes)
    write_vtu(tmp_path / "model.vtu", points, elements, {"n": np.arange(len(elements), dtype=np.int32)})
    text = (tmp_path / "model.inp").read_text()
    assert text.count("*ELEMENT, TYPE=C3D10\n") == 1 and "C3D10MH" not in text  # meshio's own name is the hybrid
    inp = meshio.read(tmp_path / "model.inp")
    assert np.array_equal(inp.cells_dict["tetra10"], elements)
    assert np.allclose(inp.points, points, rtol=0, atol=1e-6)
    assert np.array_equal(np.sort(inp.point_sets["WELD_ZONE_NODES"]), zone_nodes)
    assert len(zone_nodes) > len(solid.weld_zone_nodes())  # the zone faces' edge nodes too
    vtu = meshio.read(tmp_path / "model.vtu")
    assert np.array_equal(vtu.cells_dict["tetra10"], elements)
    with pytest.raises(ValueError, match=r"\(e, 4\) C3D4 or \(e, 10\) C3D10"):
        write_vtu(tmp_path / "bad.vtu", points, elements[:, :8], {})
