"""``weldrecon measure-weld FOLDER``: a sample of imported scans (``weldrecon import-scans`` of two
halves of a drawn T-joint's corner, each written in its own frame, placed by a .conf's poses) is
measured in the world frame as the whole corner is; a run folder's published mesh is read; any
other folder, or scans in no common frame, is one line."""

from __future__ import annotations

import json

import numpy as np

from schemas.profile_weld import ScanWeld
from tests.flows.cli import weldrecon
from tests.flows.test_import_scans_cli import _conf, _pose
from tests.flows.test_measure_fillet_cli import ALONG, ROOT, _check_figures, tjoint_corner, write_ply


def _halves_in_their_frames(folder):
    """The corner's two halves along the weld, each in its own scan frame, and their poses."""
    folder.mkdir()
    world = tjoint_corner()
    s = (world - ROOT) @ ALONG
    files, poses = [], {}
    for k, half in enumerate((world[s < 0], world[s >= 0])):
        T = _pose(10 + k)  # T_world_scan
        files.append(write_ply(folder / f"half{k}.ply", (half - T[:3, 3]) @ T[:3, :3]))
        poses[files[-1].name] = T
    _conf(folder / "scans.conf", poses, unit_mm=1.0)
    return files, folder / "scans.conf"


def test_an_imported_sample_is_measured_in_its_world_frame(tmp_path):
    files, conf = _halves_in_their_frames(tmp_path / "scans")
    sample = tmp_path / "tee-sample"
    done = weldrecon("import-scans", str(sample), *map(str, files), "--units", "mm", "--poses", str(conf))
    assert done.returncode == 0, done.stderr
    done = weldrecon("measure-weld", str(sample), "--joint", "fillet", "--out", str(tmp_path / "out"))
    assert done.returncode == 0 and done.stderr == "", done.stderr
    doc = ScanWeld.model_validate_json((tmp_path / "out" / "tee-sample.weld.json").read_text())
    assert doc.source.kind == "sample" and doc.source.files == ["passes/half0.zarr", "passes/half1.zarr"]
    assert doc.source.points == len(tjoint_corner())
    for end in (doc.weld_line.start_mm, doc.weld_line.end_mm):  # both halves put back where they were drawn
        rel = np.subtract(end, ROOT)
        assert np.linalg.norm(rel - (rel @ ALONG) * ALONG) < 0.05
    _check_figures(doc)


def test_a_run_folder_is_read_from_its_published_mesh(tmp_path):
    run = tmp_path / "runs" / "tee-017"
    (run / "results").mkdir(parents=True)
    write_ply(run / "results" / "tee-017.ply", tjoint_corner())  # the published mesh's vertices: its points
    (run / "results" / "report.json").write_text(json.dumps({"sample_id": "tee-017"}))
    done = weldrecon("measure-weld", str(run), "--joint", "fillet", "--out", str(tmp_path / "out"))
    assert done.returncode == 0 and done.stderr == "", done.stderr
    doc = ScanWeld.model_validate_json((tmp_path / "out" / "tee-017.weld.json").read_text())
    assert doc.source.kind == "run" and doc.source.files == ["results/tee-017.ply"]
    _check_figures(doc)


def test_a_folder_that_is_neither_or_scans_in_no_common_frame_is_one_line(tmp_path):
    expected = "expected a point file, a sample folder of imported scans (weldrecon import-scans"
    empty = tmp_path / "empty"
    empty.mkdir()
    (tmp_path / "unpublished" / "results").mkdir(parents=True)
    files, _ = _halves_in_their_frames(tmp_path / "scans")
    unposed = tmp_path / "unposed"
    assert weldrecon("import-scans", str(unposed), *map(str, files), "--units", "mm").returncode == 0
    for folder, says in ((empty, "a folder with neither manifest.json nor results/; " + expected),
                         (tmp_path / "unpublished", "results/ holds nothing; " + expected),
                         (unposed, "its 2 scans have no poses, so no common frame")):
        done = weldrecon("measure-weld", str(folder), "--joint", "fillet", "--out", str(tmp_path / "out"))
        assert done.returncode == 2 and len(done.stderr.splitlines()) == 1, done.stderr
        assert done.stderr.startswith(f"weldrecon measure-weld: error: {folder}: {says}"), done.stderr
