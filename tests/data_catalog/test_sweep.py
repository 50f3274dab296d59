"""Temporary files and folders carry their writer's host and pid: what a dead process left is
swept, what a live one is writing is not."""

from __future__ import annotations

import socket
import subprocess
import sys

from data_catalog.atomic import owner_tag, sweep_leftovers


def test_only_a_dead_writers_leftovers_are_swept(tmp_path):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    host = socket.gethostname()
    stage = tmp_path / "stages" / "merge"
    stage.mkdir(parents=True)
    (tmp_path / "results").mkdir()
    gone = [stage / f".build-~{host}~{dead.pid}~abc", stage / f".scratch-~{host}~{dead.pid}~x",
            tmp_path / "results" / f".report.json.~{host}~{dead.pid}~.partial"]
    kept = [stage / f".build-{owner_tag()}-live", stage / f".build-~elsewhere~{dead.pid}~abc",
            stage / ".build-untagged", stage / "0123abcd", tmp_path / "results" / "report.json"]
    for path in gone + kept:
        if path.name.endswith(".partial") or path.name == "report.json":
            path.write_text("x")
        else:
            path.mkdir()
            (path / "part").write_text("x")
    removed = sweep_leftovers(tmp_path)
    assert sorted(removed) == sorted(gone)
    assert not any(p.exists() for p in gone) and all(p.exists() for p in kept)
