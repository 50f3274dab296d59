"""``weldrecon import-scans``: point clouds written by each format's own library (plyfile, pypcd4,
laspy, pye57, numpy text) and a scanalyze .conf become a sample of imported scans (manifest +
one scan store each, points in the scan's own frame, the pose where one was given); bad input is
refused in one line naming the file (and line or field), and nothing is written."""

from __future__ import annotations

import json

import laspy
import numpy as np
import pye57
import pypcd4
import pytest
from numpy.testing import assert_allclose
from scipy.spatial.transform import Rotation

from data_catalog.manifests import load_manifest
from data_catalog.scans import read_scan
from flows.cli import main
from tests.data_catalog.test_pointclouds import _write_ply
from tests.flows.cli import run_cli

RNG = np.random.default_rng(11)
POINTS_M = RNG.uniform(-0.05, 0.05, size=(300, 3))  # a 0.1 m cube of points, metres
STORED_MM = 1e-3  # float32 at 50 mm (1e-5 mm), the LAZ file's 1 um integer step (5e-4 mm)


def _pose(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    T[:3, 3] = rng.uniform(-200, 200, size=3)
    return T


def _conf(path, poses_mm: dict, extra: str = "", *, unit_mm: float = 1000.0) -> None:
    """A scanalyze .conf (translations in a unit of ``unit_mm`` mm, default metres):
    ``p_world = R(q)^T p + t``, q scalar last."""
    lines = ["camera 0 0 0 0 0 0 1"]
    for name, T in poses_mm.items():
        q = Rotation.from_matrix(T[:3, :3].T).as_quat()
        lines.append(f"bmesh {name} " + " ".join(f"{v:.17g}" for v in [*(T[:3, 3] / unit_mm), *q]))
    path.write_text("\n".join(lines) + "\n" + extra)


def _files(folder):
    """One scan per format, each written by its own library; all in metres."""
    folder.mkdir()
    parts = np.array_split(POINTS_M, 5)
    _write_ply(folder / "a.ply", text=False, points=parts[0])
    pypcd4.PointCloud.from_xyz_points(parts[1].astype(np.float32)).save(folder / "b.pcd")
    header = laspy.LasHeader(point_format=0, version="1.2")
    header.scales, header.offsets = np.array([1e-6] * 3), np.zeros(3)
    las = laspy.LasData(header)
    las.x, las.y, las.z = parts[2].T
    las.write(folder / "c.laz")
    np.savetxt(folder / "d.xyz.gz", parts[3])
    np.savetxt(folder / "e.csv", parts[4], delimiter=",", header="x,y,z", comments="")
    return [folder / n for n in ("a.ply", "b.pcd", "c.laz", "d.xyz.gz", "e.csv")], parts


def test_import_every_format_with_conf_poses(tmp_path):
    files, parts = _files(tmp_path / "in")
    poses = {f.name: _pose(k) for k, f in enumerate(files)}
    _conf(tmp_path / "scans.conf", poses)
    out = tmp_path / "sample"
    done = run_cli("import-scans", str(out), *map(str, files), "--units", "m", "--poses", str(tmp_path / "scans.conf"),
                   "--view-direction", "0,0,2")
    assert done.returncode == 0, done.stderr
    assert done.stdout == f"{out}: 5 scans, 300 points, poses given; registration: surfaces\n"
    manifest = load_manifest(out)
    assert manifest.surfaces and manifest.specimen is None and manifest.scanner is None
    assert manifest.sample_id == "sample"
    for (_, entry), f, part in zip(manifest.passes(), files, parts):
        assert entry.kind == "scan" and entry.has_pose and entry.view_direction == (0.0, 0.0, 1.0)
        assert entry.pass_id == f.name.split(".")[0] and entry.source == f.name
        scan = read_scan(out / entry.file, pass_id=entry.pass_id)
        assert_allclose(scan.points_mm, part * 1000, atol=STORED_MM)  # the scan's own frame, mm
        assert_allclose(scan.T_world_pass, poses[f.name], atol=1e-9)
    assert "registration" in json.loads((out / "manifest.json").read_text())


def test_e57_poses_are_used_and_can_be_ignored(tmp_path):
    e57 = pye57.E57(str(tmp_path / "site.e57"), mode="w")
    rotations = [Rotation.from_euler("z", 30, degrees=True), Rotation.from_euler("x", -45, degrees=True)]
    for k, r in enumerate(rotations):
        p = POINTS_M[150 * k:150 * (k + 1)]
        e57.write_scan_raw({"cartesianX": p[:, 0], "cartesianY": p[:, 1], "cartesianZ": p[:, 2]}, name=f"st{k}",
                           rotation=np.roll(r.as_quat(), 1), translation=np.array([1.0, 2.0, 0.5 * k]))
    e57.close()
    assert main(["import-scans", str(tmp_path / "posed"), str(tmp_path / "site.e57")]) == 0
    manifest = load_manifest(tmp_path / "posed")
    assert [e.pass_id for _, e in manifest.passes()] == ["site-st0", "site-st1"]
    scan = read_scan(tmp_path / "posed" / "passes" / "site-st1.zarr", pass_id="site-st1")
    assert_allclose(scan.T_world_pass[:3, :3], rotations[1].as_matrix(), atol=1e-9)
    assert_allclose(scan.T_world_pass[:3, 3], [1000.0, 2000.0, 500.0], atol=1e-6)
    assert main(["import-scans", str(tmp_path / "free"), str(tmp_path / "site.e57"), "--ignore-poses"]) == 0
    assert not any(e.has_pose for _, e in load_manifest(tmp_path / "free").passes())


def _bad_cases(tmp_path):
    files, _ = _files(tmp_path / "in")
    ply, pcd = files[0], files[1]
    (tmp_path / "empty.ply").write_bytes(b"")
    (tmp_path / "fake.las").write_text("x y z\n1 2 3\n")
    (tmp_path / "scan.obj").write_text("v 1 2 3\n")
    np.savetxt(tmp_path / "nan.xyz", np.array([[0.0, 0.0, 0.0], [1.0, np.nan, 2.0], [3.0, 1.0, 0.0]]))
    _conf(tmp_path / "other.conf", {"a.ply": np.eye(4), "z.ply": np.eye(4)})
    _conf(tmp_path / "short.conf", {"a.ply": np.eye(4)})
    return {
        "missing file": ([str(tmp_path / "none.ply"), "--units", "m"], f"{tmp_path / 'none.ply'}: no such file"),
        "unknown extension": ([str(tmp_path / "scan.obj"), "--units", "m"],
                              f"{tmp_path / 'scan.obj'}: unknown point-cloud extension"),
        "empty file": ([str(tmp_path / "empty.ply"), "--units", "m"], f"{tmp_path / 'empty.ply'}: empty file"),
        "not what its extension says": ([str(tmp_path / "fake.las"), "--units", "m"], f"{tmp_path / 'fake.las'}:"),
        "conf names a scan not given": ([str(ply), str(pcd), "--units", "m", "--poses", str(tmp_path / "other.conf")],
                                        f"{tmp_path / 'other.conf'}: line 3: bmesh names z.ply, which is not among"),
        "conf lacks a scan given": ([str(ply), str(pcd), "--units", "m", "--poses", str(tmp_path / "short.conf")],
                                    f"{tmp_path / 'short.conf'}: no 'bmesh b.pcd ...' line"),
        "NaN": ([str(tmp_path / "nan.xyz"), "--units", "mm"], f"{tmp_path / 'nan.xyz'}"),
        "no units": ([str(ply)], f"{ply}: a .ply file does not say its length unit; give --units"),
        "unknown units": ([str(ply), "--units", "furlong"], "--units 'furlong': expected one of mm, cm, m, in"),
        "metres read as mm": ([str(ply), "--units", "mm"], f"{ply}: scan a spans"),
        "bad view direction": ([str(ply), "--units", "m", "--view-direction", "0,0,0"], "--view-direction"),
        "bad sample id": ([str(ply), "--units", "m", "--sample-id", "../x"], "--sample-id '../x'"),
    }


CASES = ["missing file", "unknown extension", "empty file", "not what its extension says", "conf names a scan not given",
         "conf lacks a scan given", "NaN", "no units", "unknown units", "metres read as mm", "bad view direction",
         "bad sample id"]


@pytest.mark.parametrize("case", CASES)
def test_bad_input_is_one_line_and_nothing_is_written(case, tmp_path, capsys):
    args, expected = _bad_cases(tmp_path)[case]
    out = tmp_path / "out" / "sample"
    assert main(["import-scans", str(out), *args]) == 2
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"weldrecon import-scans: error: {expected}"), err
    assert not out.exists() and not (out.parent.exists() and list(out.parent.iterdir()))


def test_nan_is_counted_and_the_surfaces_manifest_is_checked(tmp_path, capsys):
    args, _ = _bad_cases(tmp_path)["NaN"]
    main(["import-scans", str(tmp_path / "s"), *args])
    assert "1 point(s) with NaN or infinite coordinates" in capsys.readouterr().err
    from schemas.manifest import SampleManifest
    base = {"schema_version": "1.1", "units": "mm", "sample_id": "s", "created": "2026-11-24T00:00:00+00:00",
            "registration": "surfaces", "setups": [{"name": "scans", "passes": [
                {"kind": "scan", "pass_id": "a", "file": "passes/a.zarr", "n_points": 3, "has_pose": True,
                 "view_direction": [0, 0, 1]},
                {"kind": "scan", "pass_id": "b", "file": "passes/b.zarr", "n_points": 3, "has_pose": False,
                 "view_direction": [0, 0, 1]}]}]}
    with pytest.raises(ValueError, match="some scans have a pose and some none"):
        SampleManifest.model_validate(base)
    with pytest.raises(ValueError, match="specimen, weld, sticker_diameter_mm, scanner required"):
        SampleManifest.model_validate({**base, "registration": "targets"})
