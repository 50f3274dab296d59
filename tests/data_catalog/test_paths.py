"""The one gate for paths a description file names (``data_catalog.paths``), and what a path given
on the command line is when it is not a regular file: each refused in one line that names the
path and what it is, nothing opened that could block (a FIFO) or lead out of the folder."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from data_catalog.paths import PathRefused, not_a_file_reason, path_inside
from data_catalog.pointclouds import PointCloudFormatError, read_point_cloud
from data_catalog.textfiles import read_yaml_mapping
from tests.flows.cli import weldrecon


@pytest.fixture()
def folder(tmp_path: Path) -> Path:
    root = tmp_path / "sample"
    (root / "passes" / "a.zarr").mkdir(parents=True)
    (root / "drawing.stl").write_bytes(b"solid x\nendsolid x\n")
    (tmp_path / "outside.txt").write_text("OUTSIDE-CONTENT\n")
    return root


def test_a_path_inside_its_folder_is_returned(folder):
    assert path_inside(folder, "drawing.stl", where="m", what="the drawing") == folder / "drawing.stl"
    assert path_inside(folder, "./passes/a.zarr", where="m", what="a store", folder=True) == folder / "passes" / "a.zarr"


@pytest.mark.parametrize("name, why", [
    ("", "an empty path"),
    ("/etc/passwd", "is not a relative POSIX path"),
    ("~/x.stl", "is not a relative POSIX path"),
    ("passes\\a.zarr", "is not a relative POSIX path"),
    ("../outside.txt", "climbs out of its folder ('..')"),
    ("passes/../../outside.txt", "climbs out of its folder ('..')"),
    ("nope.stl", "no such file in"),
    ("drawing.stl/inner", "drawing.stl is a regular file, not a folder"),
    ("passes", "is a folder; expected the thing as a regular file"),
])
def test_paths_that_leave_or_miss_are_refused_by_name(folder, name, why):
    with pytest.raises(PathRefused) as caught:
        path_inside(folder, name, where="manifest.json: x.file", what="the thing")
    message = str(caught.value)
    assert message.startswith("manifest.json: x.file: ") and why in message and "\n" not in message
    assert "OUTSIDE" not in message


def test_links_are_refused_without_following_them(folder, tmp_path):
    (folder / "link.stl").symlink_to(tmp_path / "outside.txt")
    (folder / "inner-link.stl").symlink_to(folder / "drawing.stl")  # inside, but a link all the same
    (folder / "dir-link").symlink_to(folder / "passes")
    for name, part in (("link.stl", "link.stl"), ("inner-link.stl", "inner-link.stl"), ("dir-link/a.zarr", "dir-link")):
        with pytest.raises(PathRefused, match=f"'{name}': {part} is a symbolic link; expected the thing held in"):
            path_inside(folder, name, where="w", what="the thing", folder=name.endswith(".zarr"))


def test_a_fifo_a_device_and_a_socket_are_named_for_what_they_are(folder):
    os.mkfifo(folder / "pipe.stl")
    with pytest.raises(PathRefused, match=r"'pipe.stl' is a named pipe \(FIFO\); expected the thing as a regular file"):
        path_inside(folder, "pipe.stl", where="w", what="the thing")
    assert not_a_file_reason(folder / "pipe.stl") == "a named pipe (FIFO)"
    assert not_a_file_reason("/dev/null") == "a character device"
    assert not_a_file_reason(folder) == "a folder"
    assert not_a_file_reason(folder / "none") == "no such file"
    assert not_a_file_reason(folder / "drawing.stl") is None


def test_a_fifo_given_as_a_point_cloud_or_settings_is_refused_not_read(folder):
    """Reading a FIFO blocks until someone writes to it: refused by what it is instead."""
    os.mkfifo(folder / "scan.ply")
    os.mkfifo(folder / "settings.yaml")
    with pytest.raises(PointCloudFormatError, match=r"scan.ply: a named pipe \(FIFO\), expected a .ply point cloud as a "
                                                     "regular file"):
        read_point_cloud(folder / "scan.ply", units="mm")
    with pytest.raises(PointCloudFormatError, match="null.ply: a character device, expected a .ply point cloud"):
        read_point_cloud(_dev_null_ply(folder), units="mm")
    with pytest.raises(ValueError, match=r"settings.yaml: a named pipe \(FIFO\), expected .* as a regular file"):
        read_yaml_mapping(folder / "settings.yaml", "settings")


def _dev_null_ply(folder: Path) -> Path:
    """/dev/null under a .ply name (a link: the reader follows a path given to it directly)."""
    (folder / "null.ply").symlink_to("/dev/null")
    return folder / "null.ply"


def test_measure_weld_names_a_fifo_scan_in_one_line(folder):
    os.mkfifo(folder / "scan.xyz")
    done = weldrecon("measure-weld", str(folder / "scan.xyz"), "--units", "mm", "--out", str(folder / "out"))
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1 and "a named pipe (FIFO)" in done.stderr and "scan.xyz" in done.stderr, done.stderr
    assert not (folder / "out").exists()
