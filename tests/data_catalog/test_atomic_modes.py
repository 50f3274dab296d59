"""Results, reports, stage folders and samples get the permissions of a plain write (umask), not
the private 0600/0700 of the temporary files they are written as."""

from __future__ import annotations

import os
import stat

from data_catalog.atomic import atomic_directory, atomic_write_text
from data_catalog.stages import StageStore


def _mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


def test_atomic_writes_follow_the_umask(tmp_path):
    old = os.umask(0o027)
    try:
        atomic_write_text(tmp_path / "report.json", "{}\n")
        with atomic_directory(tmp_path / "sample") as folder:
            (folder / "x").write_text("x")
        build = StageStore(tmp_path / "run").build_dir("merge")
    finally:
        os.umask(old)
    assert _mode(tmp_path / "report.json") == 0o640
    assert _mode(tmp_path / "sample") == 0o750
    assert _mode(build) == 0o750
