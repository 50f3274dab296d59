"""Point clouds from other scanners' files: each format, written here by its own library, reads
back in millimetres; the Stanford range scan reads as its organized grid; every bad file is
refused with one line naming the file and the problem.

Tolerances: coordinates stored as float32 (PLY 'f4', PCD 'F 4', E57 as pye57 writes it) come back
to float32's resolution, 1e-4 mm at the 0.2 m (200 mm) scale used here; float64 stores and text
come back to 1e-9 mm; LAS/LAZ to half its integer step (0.5 um at the 1 um scale used here, 6200 km
from the origin, so the offset must be applied).
"""

from __future__ import annotations

import gzip
from pathlib import Path

import laspy
import numpy as np
import plyfile
import pye57
import pypcd4
import pytest
from numpy.testing import assert_allclose, assert_array_equal
from scipy.spatial.transform import Rotation

from data_catalog.pointclouds import (PointCloudFormatError, ScanCloud, read_conf_poses, read_point_cloud,
                                      read_point_clouds)

BUNNY = Path(__file__).resolve().parents[3] / "shared" / "data" / "stanford-bunny" / "bun000.ply"
FLOAT32_MM = 1e-4  # float32 at 200 mm
RNG = np.random.default_rng(7)
POINTS_M = RNG.uniform(-0.1, 0.2, size=(200, 3))  # a 0.3 m cube, metres
INTENSITY = RNG.integers(0, 1024, size=200).astype(np.float32)
NORMALS = RNG.normal(size=(200, 3))
NORMALS /= np.linalg.norm(NORMALS, axis=1, keepdims=True)


def _refused(path, *phrases, units="mm", error=PointCloudFormatError):
    with pytest.raises(error) as info:
        read_point_clouds(path, units=units)
    message = str(info.value)
    assert str(path) in message and "\n" not in message, message
    for phrase in phrases:
        assert phrase in message, message
    return message


def _write_ply(path, *, text, normals=False, intensity=False, coord="f4", points=POINTS_M):
    fields = [("x", coord), ("y", coord), ("z", coord)]
    fields += [("nx", "f4"), ("ny", "f4"), ("nz", "f4")] if normals else []
    fields += [("intensity", "u2")] if intensity else []
    vertex = np.zeros(len(points), dtype=fields)
    vertex["x"], vertex["y"], vertex["z"] = points.T
    if normals:
        vertex["nx"], vertex["ny"], vertex["nz"] = NORMALS[:len(points)].T
    if intensity:
        vertex["intensity"] = INTENSITY[:len(points)]
    plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex")], text=text).write(str(path))
    return path


# -- round trips ----------------------------------------------------------------------------------

@pytest.mark.parametrize("text", [False, True], ids=["binary", "ascii"])
@pytest.mark.parametrize("extras", [False, True], ids=["xyz", "normals+intensity"])
def test_ply_round_trip(tmp_path, text, extras):
    scan = read_point_cloud(_write_ply(tmp_path / "scan.PLY", text=text, normals=extras, intensity=extras), units="m")
    assert isinstance(scan, ScanCloud) and scan.format == "ply" and scan.scan_name == "scan"
    assert scan.points_mm.dtype == np.float64 and scan.points_mm.shape == (200, 3)
    assert_allclose(scan.points_mm, POINTS_M * 1000, atol=FLOAT32_MM)
    assert scan.grid_shape is None and scan.grid_index is None and scan.T_world_scan is None
    if extras:
        assert_allclose(scan.normals, NORMALS, atol=1e-6)
        assert scan.intensity.dtype == np.float32
        assert_array_equal(scan.intensity, INTENSITY)
    else:
        assert scan.normals is None and scan.intensity is None


def test_ply_double_in_inches(tmp_path):
    scan = read_point_cloud(_write_ply(tmp_path / "s.ply", text=False, coord="f8"), units="in")
    assert_allclose(scan.points_mm, POINTS_M * 25.4, atol=1e-9)


@pytest.mark.parametrize("encoding", list(pypcd4.Encoding), ids=lambda e: e.value)
def test_pcd_round_trip(tmp_path, encoding):
    data = np.column_stack([POINTS_M, NORMALS, INTENSITY])
    cloud = pypcd4.PointCloud.from_points(data, ("x", "y", "z", "normal_x", "normal_y", "normal_z", "intensity"),
                                          (np.float32,) * 7)
    cloud.save(tmp_path / "scan.pcd", encoding=encoding)
    scan = read_point_cloud(tmp_path / "scan.pcd", units="m")
    assert scan.format == "pcd" and scan.grid_shape is None
    assert_allclose(scan.points_mm, POINTS_M * 1000, atol=FLOAT32_MM)
    assert_allclose(scan.normals, NORMALS, atol=1e-6)
    assert_array_equal(scan.intensity, INTENSITY)


def test_organized_pcd_drops_cells_without_a_return(tmp_path):
    points = POINTS_M[:12].copy()
    points[[2, 7]] = np.nan  # PCL's organized clouds mark a cell without a return with NaN
    cloud = pypcd4.PointCloud.from_xyz_points(points)
    cloud.metadata = cloud.metadata.model_copy(update={"width": 4, "height": 3})
    cloud.save(tmp_path / "organized.pcd")
    scan = read_point_cloud(tmp_path / "organized.pcd", units="m")
    assert scan.grid_shape == (3, 4)
    assert_array_equal(scan.grid_index, [0, 1, 3, 4, 5, 6, 8, 9, 10, 11])
    assert_allclose(scan.points_mm, points[scan.grid_index] * 1000, atol=FLOAT32_MM)


@pytest.mark.parametrize("name, delimiter, header, gz", [
    ("scan.xyz", " ", "", False),
    ("scan.csv", ",", "x,y,z,intensity", False),
    ("scan.TXT", "\t", "X\tY\tZ\tI", False),
    ("scan.xyz.gz", " ", "# exported", True),
    ("scan.csv.gz", ",", "x,y,z,intensity", True),
])
def test_ascii_round_trip(tmp_path, name, delimiter, header, gz):
    points_cm = POINTS_M * 100
    np.savetxt(tmp_path / name, np.column_stack([points_cm, INTENSITY]), delimiter=delimiter, header=header,
               comments="")
    if gz:
        assert (tmp_path / name).read_bytes()[:2] == b"\x1f\x8b"  # numpy gzips a .gz name
    scan = read_point_cloud(tmp_path / name, units="cm")
    assert scan.format == name.lower().split(".")[1] and scan.scan_name == "scan"
    assert_allclose(scan.points_mm, points_cm * 10, atol=1e-9)
    assert_array_equal(scan.intensity, INTENSITY)


def test_ascii_xyz_only_with_comment_lines(tmp_path):
    np.savetxt(tmp_path / "p.xyz", POINTS_M, header="from a scanner\nunits: m")  # '# ' comment lines
    scan = read_point_cloud(tmp_path / "p.xyz", units="m")
    assert scan.intensity is None
    assert_allclose(scan.points_mm, POINTS_M * 1000, atol=1e-9)


def _write_e57(path, scans):
    e57 = pye57.E57(str(path), mode="w")
    for name, points, q_wxyz, t_m, extra in scans:
        data = {"cartesianX": points[:, 0], "cartesianY": points[:, 1], "cartesianZ": points[:, 2], **extra}
        e57.write_scan_raw(data, name=name, rotation=np.asarray(q_wxyz, float), translation=np.asarray(t_m, float))
    e57.close()
    return path


def test_e57_two_scans_with_poses(tmp_path):
    poses = [Rotation.from_euler("xyz", [10, -20, 30], degrees=True), Rotation.from_euler("z", 90, degrees=True)]
    translations_m = [np.array([1.5, -0.25, 0.75]), np.array([0.0, 2.0, 0.1])]
    rows, cols = np.divmod(np.arange(100), 10)
    extras = [{"intensity": INTENSITY[:100] / 1023},
              {"rowIndex": rows.astype(np.int32), "columnIndex": cols.astype(np.int32)}]
    scans = [(f"station {i}", POINTS_M[100 * i:100 * (i + 1)], np.roll(r.as_quat(), 1), t, extra)
             for i, (r, t, extra) in enumerate(zip(poses, translations_m, extras))]
    path = _write_e57(tmp_path / "site.e57", scans)
    clouds = read_point_clouds(path)  # metres by the standard: no units needed
    assert [c.scan_name for c in clouds] == ["station 0", "station 1"]
    for cloud, (_, points_m, _, _, _), r, t_m in zip(clouds, scans, poses, translations_m):
        assert cloud.format == "e57"
        assert_allclose(cloud.points_mm, points_m * 1000, atol=FLOAT32_MM)  # in the scan's own frame
        expected = np.eye(4)
        expected[:3, :3], expected[:3, 3] = r.as_matrix(), t_m * 1000
        assert_allclose(cloud.T_world_scan, expected, atol=1e-9)
        world_mm = cloud.points_mm @ cloud.T_world_scan[:3, :3].T + cloud.T_world_scan[:3, 3]
        assert_allclose(world_mm, r.apply(points_m) * 1000 + t_m * 1000, atol=1e-3)
    assert_allclose(clouds[0].intensity, INTENSITY[:100] / 1023, atol=1e-6)
    assert clouds[0].grid_shape is None and clouds[1].intensity is None
    assert clouds[1].grid_shape == (10, 10)
    assert_array_equal(clouds[1].grid_index, np.arange(100))
    assert read_point_clouds(path, units="m")[1].scan_name == "station 1"
    with pytest.raises(PointCloudFormatError, match="holds 2 scans"):
        read_point_cloud(path)


@pytest.mark.parametrize("suffix", ["las", "laz"])
def test_las_and_laz_apply_scale_and_offset(tmp_path, suffix):
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales = np.array([1e-6, 1e-6, 1e-6])  # integer micrometres in metre units
    header.offsets = np.array([512000.0, 6200000.0, 40.0])  # a UTM-like origin
    las = laspy.LasData(header)
    points_m = header.offsets + POINTS_M
    las.x, las.y, las.z = points_m.T
    las.intensity = INTENSITY.astype(np.uint16)
    las.write(tmp_path / f"survey.{suffix}")
    if suffix == "laz":
        assert b"laszip encoded" in (tmp_path / "survey.laz").read_bytes()  # laspy compressed it (lazrs)
    scan = read_point_cloud(tmp_path / f"survey.{suffix}", units="m")
    assert scan.format == suffix
    assert_allclose(scan.points_mm, points_m * 1000, atol=0.5e-3 + 1e-6)  # half the 1 um integer step
    assert_array_equal(scan.intensity, INTENSITY)


@pytest.fixture(scope="module")
def bunny():
    if not BUNNY.is_file():
        pytest.skip(f"the Stanford bunny scans are not at {BUNNY.parent} (../shared/data beside the repository)")
    return read_point_cloud(BUNNY, units="m")


def test_stanford_range_scan_is_an_organized_grid(bunny):
    assert bunny.grid_shape == (400, 512)  # obj_info num_rows 400, num_cols 512
    assert bunny.points_mm.shape == (40256, 3)  # element vertex 40256
    g = bunny.grid_index
    assert g.min() >= 0 and g.max() < 400 * 512 and len(np.unique(g)) == len(g)  # one cell per vertex
    size_mm = np.ptp(bunny.points_mm, axis=0)
    assert 100 < size_mm.max() < 200, size_mm  # a bunny about 15 cm across, metres read as mm
    # neighbouring cells hold neighbouring points: the grid is row by row (row * cols + col)
    rows, cols = np.divmod(g, 512)
    cell = np.full(400 * 512, -1)
    cell[g] = np.arange(len(g))
    right = cell[np.where(cols < 511, g + 1, g)]
    has = (cols < 511) & (right >= 0)
    step = np.linalg.norm(bunny.points_mm[has] - bunny.points_mm[right[has]], axis=1)
    assert np.median(step) < 1.0  # 0.5 mm line increment (echo_lgincr 0.0005 m)


# -- refusals -------------------------------------------------------------------------------------

def test_units_are_required_and_checked(tmp_path):
    path = _write_ply(tmp_path / "s.ply", text=False)
    _refused(path, "does not say its length unit", "units='mm'", units=None, error=ValueError)
    _refused(path, "units must be one of", units="km", error=ValueError)
    e57 = _write_e57(tmp_path / "s.e57", [("a", POINTS_M, [1, 0, 0, 0], [0, 0, 0], {})])
    _refused(e57, "metres by the standard", units="mm", error=ValueError)
    with pytest.raises(FileNotFoundError, match="nope.ply"):
        read_point_cloud(tmp_path / "nope.ply", units="mm")


@pytest.mark.parametrize("name", ["scan.obj", "scan.ply.gz", "scan"])
def test_unknown_extension(tmp_path, name):
    (tmp_path / name).write_text("1 2 3\n")
    _refused(tmp_path / name, "unknown point-cloud extension", ".ply", ".laz")


@pytest.mark.parametrize("name", ["e.ply", "e.pcd", "e.xyz", "e.e57", "e.las", "e.csv.gz"])
def test_empty_file(tmp_path, name):
    (tmp_path / name).write_bytes(b"")
    _refused(tmp_path / name, "empty file (0 bytes)", units=None if name.endswith(".e57") else "mm")


def test_zero_points(tmp_path):
    _refused(_write_ply(tmp_path / "z.ply", text=True, points=np.zeros((0, 3))), "no points")
    np.savetxt(tmp_path / "z.csv", np.zeros((0, 3)), delimiter=",", header="x,y,z", comments="")
    _refused(tmp_path / "z.csv", "no points")
    pypcd4.PointCloud.from_xyz_points(np.zeros((0, 3), np.float32)).save(tmp_path / "z.pcd")
    _refused(tmp_path / "z.pcd", "no points")
    laspy.LasData(laspy.LasHeader(point_format=0, version="1.2")).write(tmp_path / "z.las")
    _refused(tmp_path / "z.las", "point_count is 0")
    e57 = pye57.E57(str(tmp_path / "z.e57"), mode="w")
    e57.close()
    _refused(tmp_path / "z.e57", "no scans", units=None)


PNG = b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 4


@pytest.mark.parametrize("name, phrase", [
    ("png.ply", "not a valid PLY file: it starts with b'\\x89PNG"), ("png.e57", "not a valid E57 file"),
    ("png.pcd", "not a readable PCD file"), ("png.xyz", "not readable as UTF-8 text: "),
    ("png.xyz.gz", "not a gzip file"),
])
def test_a_png_renamed(tmp_path, name, phrase):
    (tmp_path / name).write_bytes(PNG)
    _refused(tmp_path / name, phrase, units=None if name.endswith(".e57") else "mm")


@pytest.mark.parametrize("suffix", ["las", "laz"])
def test_text_in_a_las(tmp_path, suffix):
    (tmp_path / f"t.{suffix}").write_text("x y z\n1 2 3\n")
    _refused(tmp_path / f"t.{suffix}", f"not a valid {suffix.upper()} file", "expected b'LASF'")


def test_broken_files_keep_the_library_text(tmp_path):
    ply = _write_ply(tmp_path / "cut.ply", text=False)
    ply.write_bytes(ply.read_bytes()[:-50])  # binary body cut short
    _refused(ply, "not a readable PLY file: ", "vertex")
    las = tmp_path / "cut.las"
    header = laspy.LasHeader(point_format=0, version="1.2")
    data = laspy.LasData(header)
    data.x, data.y, data.z = POINTS_M.T
    data.write(las)
    las.write_bytes(las.read_bytes()[:300])  # the header survives, the points do not
    _refused(las, "not a readable LAS file (expected a LAS header and its point records): ")
    e57 = _write_e57(tmp_path / "cut.e57", [("a", POINTS_M, [1, 0, 0, 0], [0, 0, 0], {})])
    e57.write_bytes(e57.read_bytes()[:2000])
    _refused(e57, "not a readable E57 file: ", units=None)


def test_broken_gzip(tmp_path):
    np.savetxt(tmp_path / "p.xyz.gz", POINTS_M)
    whole = (tmp_path / "p.xyz.gz").read_bytes()
    (tmp_path / "cut.xyz.gz").write_bytes(whole[:len(whole) // 2])
    _refused(tmp_path / "cut.xyz.gz", "not readable as gzip-compressed text: ")
    damaged = bytearray(whole)
    damaged[len(whole) // 2] ^= 0xFF
    (tmp_path / "bad.xyz.gz").write_bytes(bytes(damaged))
    _refused(tmp_path / "bad.xyz.gz", "not readable as gzip-compressed text: ")


def test_ascii_wrong_column_count_names_the_line(tmp_path):
    (tmp_path / "a.xyz").write_text("x y z\n1 2 3\n4 5 6\n\n7 8 9 10\n")
    _refused(tmp_path / "a.xyz", "line 5: 4 columns, expected 3")
    (tmp_path / "b.csv").write_text("1,2\n3,4\n")
    _refused(tmp_path / "b.csv", "line 1: 2 columns, expected 3 or 4")
    (tmp_path / "c.txt").write_text("1 2 3 4 5\n")
    _refused(tmp_path / "c.txt", "line 1: 5 columns, expected 3 or 4")
    (tmp_path / "d.csv").write_text("x,y,z\n1,2,3\n4,five,6\n")
    _refused(tmp_path / "d.csv", "line 3: expected numbers", "five")


def test_non_finite_coordinates_are_counted(tmp_path):
    (tmp_path / "n.xyz").write_text("# header comment\n1 2 3\nnan 2 3\n4 5 6\n7 inf 9\n")
    _refused(tmp_path / "n.xyz", "2 point(s) with NaN or infinite", "the first at line 3")
    points = POINTS_M.copy()
    points[[5, 9, 11], 2] = [np.nan, np.inf, -np.inf]
    _refused(_write_ply(tmp_path / "n.ply", text=False, points=points), "3 point(s)", "the first at point 5 (from 0)")


def test_missing_coordinate_fields(tmp_path):
    vertex = np.zeros(3, dtype=[("x", "f4"), ("y", "f4"), ("intensity", "u2")])
    plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex")]).write(str(tmp_path / "xy.ply"))
    _refused(tmp_path / "xy.ply", "element 'vertex' has no z field", "expected x, y, z")
    face = np.zeros(1, dtype=[("vertex_indices", "O")])
    face["vertex_indices"][0] = np.array([0, 1, 2], dtype=np.int32)
    plyfile.PlyData([plyfile.PlyElement.describe(face, "face")]).write(str(tmp_path / "nov.ply"))
    _refused(tmp_path / "nov.ply", "no 'vertex' element")
    pypcd4.PointCloud.from_points(np.ones((3, 3)), ("x", "y", "intensity"), (np.float32,) * 3).save(
        tmp_path / "xy.pcd")
    _refused(tmp_path / "xy.pcd", "FIELDS has no z field")


def _write_range_grid(path, cells, *, obj_info=("num_cols 3", "num_rows 2")):
    vertex = np.zeros(4, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    vertex["z"] = np.arange(4)
    grid = np.empty(len(cells), dtype=[("vertex_indices", "O")])
    grid["vertex_indices"] = [np.array(c, dtype=np.int32) for c in cells]
    elements = [plyfile.PlyElement.describe(vertex, "vertex"),
                plyfile.PlyElement.describe(grid, "range_grid", val_types={"vertex_indices": "i4"})]
    plyfile.PlyData(elements, text=True, obj_info=list(obj_info)).write(str(path))
    return path


def test_small_range_grid_round_trip(tmp_path):
    scan = read_point_cloud(_write_range_grid(tmp_path / "g.ply", [[], [0], [1], [2], [], [3]]), units="mm")
    assert scan.grid_shape == (2, 3)
    assert_array_equal(scan.grid_index, [1, 2, 3, 5])


def test_bad_range_grids(tmp_path):
    _refused(_write_range_grid(tmp_path / "past.ply", [[], [0], [1], [2], [], [7]]),
             "element 'range_grid' cell 5 points to vertex 7", "below the 4 vertices")
    _refused(_write_range_grid(tmp_path / "count.ply", [[0], [1], [2], [3]]),
             "element 'range_grid' has 4 cells, expected", "2 x 3 = 6")
    _refused(_write_range_grid(tmp_path / "info.ply", [[0], [1], [2], [3], [], []], obj_info=("num_cols 3",)),
             "needs 'obj_info num_rows N'", "found num_rows ''")
    _refused(_write_range_grid(tmp_path / "twice.ply", [[0], [0], [1], [2], [3], []]), "more than one cell")


def test_conf_poses_follow_scanalyzes_convention(tmp_path):
    """``bmesh FILE t q``: p_world = R(q)^T p + t (the transpose: scanalyze keeps OpenGL's column-major
    matrix), quaternion scalar last, translations in the unit given; the bunny's own file reads."""
    q = Rotation.from_euler("xyz", [10.0, -20.0, 30.0], degrees=True)
    x, y, z, w = q.as_quat()
    conf = tmp_path / "scans.conf"
    conf.write_text(f"camera 0 0 0 0 0 0 1\nbmesh a.ply 0.1 -0.2 0.3 {x} {y} {z} {w}\n\nbmesh b.ply 0 0 0 0 0 0 1\n")
    poses = read_conf_poses(conf, units="m")
    assert list(poses) == ["a.ply", "b.ply"]
    assert_allclose(poses["a.ply"][:3, :3], q.as_matrix().T, atol=1e-12)
    assert_allclose(poses["a.ply"][:3, 3], [100.0, -200.0, 300.0], atol=1e-9)
    assert_array_equal(poses["b.ply"], np.eye(4))
    if BUNNY.is_file():
        bunny = read_conf_poses(BUNNY.with_name("bun.conf"), units="m")
        assert len(bunny) == 10
        assert_array_equal(bunny["bun000.ply"], np.eye(4))


@pytest.mark.parametrize("line, problem", [
    ("bmesh a.ply 0 0 0 0 0 0", "expected 'bmesh FILE tx ty tz qx qy qz qw'"),
    ("bmesh a.ply 0 0 zero 0 0 0 1", "expected 'bmesh FILE tx ty tz qx qy qz qw'"),
    ("bmesh a.ply 0 0 0 0 0 0 2", "with a unit quaternion"),
    ("bmesh a.ply 0 0 0 0 0 0 nan", "with a unit quaternion"),
    ("bmesh a.ply 1e30 0 0 0 0 0 1", r"a.ply's translation reaches 1e\+33 mm from the origin \(read in m\); expected a "
                                     "pose within 50 m of it"),
    ("bmesh a.ply 0 0 60 0 0 0 1", r"a.ply's translation reaches 6e\+04 mm"),
    ("bmesh a.ply 0 inf 0 0 0 0 1", "expected 'bmesh FILE tx ty tz qx qy qz qw'"),
])
def test_a_malformed_conf_line_is_named(tmp_path, line, problem):
    conf = tmp_path / "scans.conf"
    conf.write_text(f"camera 0 0 0 0 0 0 1\n{line}\n")
    with pytest.raises(PointCloudFormatError, match=f"{conf}: line 2: .*{problem}"):
        read_conf_poses(conf, units="m")


def test_a_conf_without_poses_or_with_a_scan_twice_is_refused(tmp_path):
    conf = tmp_path / "scans.conf"
    conf.write_text("camera 0 0 0 0 0 0 1\n")
    with pytest.raises(PointCloudFormatError, match="no 'bmesh FILE tx ty tz qx qy qz qw' line"):
        read_conf_poses(conf, units="m")
    conf.write_text("bmesh a.ply 0 0 0 0 0 0 1\nbmesh a.ply 0 0 0 0 0 0 1\n")
    with pytest.raises(PointCloudFormatError, match="line 2: a.ply has a pose already"):
        read_conf_poses(conf, units="m")
    with pytest.raises(ValueError, match="units must be one of"):
        read_conf_poses(conf, units="furlong")


# -- what a header claims against the data --------------------------------------------------------

def _claim(path, old: bytes, new: bytes):
    data = path.read_bytes()
    assert old in data[:400]
    path.write_bytes(data.replace(old, new, 1))
    return path


@pytest.mark.parametrize("text", [False, True], ids=["binary", "ascii"])
def test_a_ply_header_counting_fewer_points_than_its_data_is_refused(tmp_path, text):
    """plyfile stops at the declared count and drops the rest without a word: refused, with both counts."""
    path = _claim(_write_ply(tmp_path / "scan.ply", text=text), b"element vertex 200", b"element vertex 150")
    if text:
        _refused(path, "200 data lines after the header, which declares 150 rows (element vertex 150)",
                 "expected the header's counts to be the file's")
    else:
        _refused(path, "600 bytes after the data its header declares (element vertex 150)")


@pytest.mark.parametrize("text", [False, True], ids=["binary", "ascii"])
def test_a_ply_header_counting_more_points_than_its_data_is_refused(tmp_path, text):
    path = _claim(_write_ply(tmp_path / "scan.ply", text=text), b"element vertex 200", b"element vertex 250")
    _refused(path, "not a readable PLY file", "early end-of-file")


@pytest.mark.parametrize("encoding", [pypcd4.Encoding.ASCII, pypcd4.Encoding.BINARY], ids=["ascii", "binary"])
@pytest.mark.parametrize("claim", [150, 250])
def test_a_pcd_header_disagreeing_with_its_data_is_refused(tmp_path, encoding, claim):
    """pypcd4 reads what is there, more or fewer than POINTS, without a word: refused."""
    cloud = pypcd4.PointCloud.from_xyz_points(POINTS_M.astype(np.float32))
    cloud.save(tmp_path / "scan.pcd", encoding=encoding)
    path = _claim(tmp_path / "scan.pcd", b"POINTS 200", f"POINTS {claim}".encode())
    _claim(path, b"WIDTH 200", f"WIDTH {claim}".encode())
    _refused(path, f"POINTS {claim} in the header, 200 points of data", "expected the header's count to be the file's")


def test_a_pcd_whose_width_and_height_disagree_with_points_is_refused(tmp_path):
    cloud = pypcd4.PointCloud.from_xyz_points(POINTS_M.astype(np.float32))
    cloud.save(tmp_path / "scan.pcd", encoding=pypcd4.Encoding.BINARY)
    path = _claim(tmp_path / "scan.pcd", b"WIDTH 200", b"WIDTH 100")
    _refused(path, "WIDTH x HEIGHT = 100 x 1 = 100, POINTS 200; expected them equal")


def test_a_gzip_of_zeros_is_refused_at_its_first_megabyte(tmp_path):
    path = tmp_path / "scan.xyz.gz"
    with gzip.open(path, "wb", compresslevel=1) as handle:
        for _ in range(16):
            handle.write(b"\0" * (1 << 20))
    _refused(path, "a line longer than 1,048,576 bytes decompressed; expected lines of x y z [intensity]")


def test_one_line_repeated_millions_of_times_is_refused_as_a_bomb(tmp_path):
    """98 million identical lines ran past 300 s before; a ratio over 100 is refused once 64 MiB are out."""
    path = tmp_path / "scan.xyz.gz"
    block = b"1.000 2.000 3.000\n" * 100_000
    with gzip.open(path, "wb") as handle:
        for _ in range(40):  # 72 MB of text
            handle.write(block)
    _refused(path, "decompresses to more than 100 times its", "expected scanned points, which compress 3-5 times")


def test_an_overlong_line_among_good_ones_is_refused_wherever_the_blocks_cut_it(tmp_path):
    good = "".join(f"{k} {k} {k}\n" for k in range(200_000))  # ~2.5 MB: several 1 MiB blocks
    path = tmp_path / "scan.xyz"
    path.write_text(good[: len(good) // 2] + "9" * (1_100_000) + " 1 1\n" + good[len(good) // 2:])
    _refused(path, "a line longer than 1,048,576 bytes; expected lines of x y z [intensity]")
    path.write_text(good)
    assert len(read_point_cloud(path, units="mm").points_mm) == 200_000
