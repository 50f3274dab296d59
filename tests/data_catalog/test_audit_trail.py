"""The audit trail survives a write that was cut short (a crash, a full disk): the damaged tail is
set aside with a record of it, never trusted and never blocking the folder; damage in the middle
is named (file, line, cause); a failed append leaves the trail as it was."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
from pathlib import Path

import pytest

from data_catalog import audit
from data_catalog.audit import TRAIL, TrailError, read_trail, verify_trail


def _trail(tmp_path: Path, n: int = 3) -> Path:
    run = tmp_path / "run"
    for k in range(n):
        audit.append(run, "stage", stage="denoise", item=f"p{k}")
    return run


@pytest.mark.parametrize("tail, cause", [
    (b'{"seq": 3, "prev": "ab', "no line end"),
    (b'{"seq": 3, "kind": "st\xff\xfeage"}\n', "not UTF-8"),
    (b'{"seq": 3, "kind": \n', "not valid JSON"),
])
def test_a_damaged_tail_is_set_aside_and_recorded_and_the_folder_goes_on(tmp_path, tail, cause):
    run = _trail(tmp_path)
    path = run / TRAIL
    good = path.read_bytes()
    with open(path, "ab") as f:
        f.write(tail)
    # read and verify name the line and the cause
    assert read_trail(run)[-1]["_unreadable"].startswith(f"line 4: {cause}")
    assert any("trail line 4" in str(p) and cause in str(p) for p in verify_trail(run))
    # the next append sets the tail aside, records it, and goes on
    entry = audit.append(run, "run-finished", sample_id="s")
    entries = read_trail(run)
    assert [e["kind"] for e in entries] == ["stage"] * 3 + ["trail-damage-set-aside", "run-finished"]
    record = entries[3]
    assert record["lines"] == [4] and record["bytes"] == len(tail) and cause in record["cause"]
    assert record["sha256"] == hashlib.sha256(tail).hexdigest()
    assert (run / record["kept_at"]).read_bytes() == tail
    assert path.read_bytes().startswith(good) and entry["seq"] == 4
    assert verify_trail(run) == []


def test_damage_with_entries_after_it_is_named_and_nothing_is_changed(tmp_path):
    run = _trail(tmp_path)
    path = run / TRAIL
    lines = path.read_bytes().splitlines(keepends=True)
    lines[1] = b'{"seq": 1, \xff broken}\n'
    path.write_bytes(b"".join(lines))
    before = path.read_bytes()
    with pytest.raises(TrailError) as err:
        audit.append(run, "run-finished", sample_id="s")
    assert str(err.value).startswith(f"{path} line 2: not UTF-8")
    assert "not a cut-short write" in str(err.value)
    assert path.read_bytes() == before and not (path.parent / "damaged").exists()


def test_a_full_disk_leaves_the_trail_as_it_was_and_the_folder_recovers(tmp_path):
    mount = tmp_path / "small"
    mount.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(mount)],
                      capture_output=True).returncode != 0:
        pytest.skip("cannot mount a tmpfs here (needs root)")
    try:
        run = mount / "run"
        audit.append(run, "run-started", sample_id="s")
        before = (run / TRAIL).read_bytes()
        filler = mount / "filler"
        with open(filler, "wb", buffering=0) as f:  # fill the disk to the last byte
            for size in (4096, 1):
                try:
                    while True:
                        f.write(b"\0" * size)
                except OSError:
                    pass
        with pytest.raises(TrailError) as err:
            audit.append(run, "stage", stage="denoise", item="p0", record={"blob": "x" * 20000})
        assert str(err.value) == (f"{run / TRAIL}: could not append an audit entry (No space left on device); "
                                  "the trail is as it was before")
        assert (run / TRAIL).read_bytes() == before
        filler.unlink()  # space freed: the folder goes on
        audit.append(run, "stage", stage="denoise", item="p0")
        audit.append(run, "run-finished", sample_id="s")
        assert [e["kind"] for e in read_trail(run)] == ["run-started", "stage", "run-finished"]
        assert verify_trail(run) == []
    finally:
        subprocess.run(["umount", str(mount)], check=False)


def test_entries_are_whole_lines_of_json(tmp_path):
    run = _trail(tmp_path, n=2)
    raw = (run / TRAIL).read_bytes()
    assert raw.endswith(b"\n") and all(json.loads(line)["hash"] for line in raw.splitlines())
    assert os.stat(run / TRAIL).st_size == len(raw)


def test_each_problem_carries_a_kind_that_programs_can_rely_on(tmp_path):
    """Programs (a rerun deciding what to record) read a problem's kind, never its wording."""
    run = _trail(tmp_path, 4)
    audit.append(run, "run-started", sample_id="s")
    path = run / TRAIL
    lines = path.read_bytes().splitlines(keepends=True)
    edited = json.loads(lines[1])
    edited["item"] = "p9"  # an edited entry (its hash no longer matches)
    lines[1] = (json.dumps(edited) + "\n").encode()
    del lines[2]  # a removed entry (sequence and chain broken)
    path.write_bytes(b"".join(lines))
    (run / "stages" / "mesh" / "abc").mkdir(parents=True)  # a stage folder no entry records
    kinds = sorted({p.kind for p in verify_trail(run, heads={"0" * 64: "the catalog"})})
    assert kinds == ["chain", "edited", "head-missing", "sequence", "unfinished-run", "unrecorded"]


def test_a_later_run_that_publishes_fewer_results_leaves_the_trail_intact(tmp_path):
    """results/ is replaced as a whole on publication: a rerun that publishes no FE model (it was
    not made this time) does not leave the earlier run's model expected; one still lying there is
    named as recorded by no run."""
    from data_catalog.hashing import sha256_file

    run = tmp_path / "run"
    results = run / "results"
    results.mkdir(parents=True)
    for name in ("s.stl", "s.inp"):
        (results / name).write_text(name)
    audit.append(run, "run-started", sample_id="s")
    audit.append(run, "run-finished", sample_id="s",
                 artefacts={f"results/{n}": sha256_file(results / n) for n in ("s.stl", "s.inp")})
    (results / "s.inp").unlink()  # the rerun's publication replaced results/ without it
    audit.append(run, "run-started", sample_id="s")
    audit.append(run, "run-finished", sample_id="s", artefacts={"results/s.stl": sha256_file(results / "s.stl")})
    assert verify_trail(run) == []
    (results / "s.inp").write_text("s.inp")  # put back by hand: no run published it
    assert any("results/s.inp" in str(p) and "no run-finished entry records" in str(p) for p in verify_trail(run))
