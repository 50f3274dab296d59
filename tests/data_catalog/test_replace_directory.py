"""Results are published as one folder swapped in whole (``replace_directory``): a reader, or a
kill -9 at any instant, sees the previous set or the next, never a mix."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from data_catalog import atomic
from data_catalog.atomic import replace_directory, sweep_leftovers

REPO = Path(__file__).resolve().parents[2]


def _folder(path: Path, files: dict[str, str]) -> Path:
    path.mkdir()
    for name, text in files.items():
        (path / name).write_text(text)
    return path


@pytest.mark.parametrize("exchange", [True, False], ids=["exchange", "rename-aside"])
def test_the_old_folder_is_replaced_whole(tmp_path, monkeypatch, exchange):
    if not exchange:  # a filesystem that cannot swap two folders at once
        monkeypatch.setattr(atomic, "_exchange", lambda a, b: False)
    target = tmp_path / "results"
    replace_directory(_folder(tmp_path / "new1", {"a.stl": "1", "report.json": "1"}), target)
    assert {p.name: p.read_text() for p in target.iterdir()} == {"a.stl": "1", "report.json": "1"}
    replace_directory(_folder(tmp_path / "new2", {"b.stl": "2", "report.json": "2"}), target)
    assert {p.name: p.read_text() for p in target.iterdir()} == {"b.stl": "2", "report.json": "2"}  # no a.stl left
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results"]


_WRITER = textwrap.dedent("""
    import itertools, sys, tempfile
    from pathlib import Path
    from data_catalog.atomic import owner_tag, replace_directory, fsync_tree
    root = Path(sys.argv[1])
    for generation in itertools.count():
        staging = Path(tempfile.mkdtemp(prefix=f".results.{owner_tag()}.", suffix=".partial", dir=root))
        for name in ("sample.stl", "sample.ply", "report.json", "config.json"):
            (staging / name).write_text(f"{generation}\\n" * (1 + generation % 50))
        fsync_tree(staging)
        replace_directory(staging, root / "results")
        if generation == 0:
            print("first", flush=True)
""")


def _read_whole(folder: Path) -> set[str] | None:
    """The generations the files of the folder at ``folder`` hold, read through one handle on it.
    None when that folder was replaced before the read ended (the reader reads again): what is
    checked is every read of the folder that is still the published one after it."""
    try:
        fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    except FileNotFoundError:
        return None
    try:
        names, seen = os.listdir(fd), set()
        for name in names:
            with open(name, opener=lambda path, flags: os.open(path, flags, dir_fd=fd)) as handle:
                seen |= set(handle.read().split())
    except FileNotFoundError:
        names = None
    try:
        if names is None or os.stat(folder).st_ino != os.fstat(fd).st_ino:
            return None  # replaced meanwhile: the old folder is being removed
    except FileNotFoundError:
        return None
    finally:
        os.close(fd)
    assert sorted(names) == ["config.json", "report.json", "sample.ply", "sample.stl"], names
    return seen


def test_readers_and_kills_never_see_a_mixed_results_folder(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(REPO))
    reads = 0
    for delay in (0.05, 0.13, 0.21, 0.34, 0.55):
        writer = subprocess.Popen([sys.executable, "-c", _WRITER, str(tmp_path)], env=env, stdout=subprocess.PIPE,
                                  text=True)
        try:
            assert writer.stdout.readline() == "first\n"
            deadline = time.monotonic() + delay
            while time.monotonic() < deadline:
                seen = _read_whole(tmp_path / "results")
                if seen is not None:
                    assert len(seen) == 1, f"a mixed results folder: generations {sorted(seen)}"
                    reads += 1
        finally:
            writer.send_signal(signal.SIGKILL)
            writer.wait()
            writer.stdout.close()
        seen = _read_whole(tmp_path / "results")
        assert seen is not None and len(seen) == 1  # whatever instant the kill came at
        sweep_leftovers(tmp_path)  # what the dead writer left half built
        assert sorted(p.name for p in tmp_path.iterdir()) == ["results"]
    assert reads > 50
