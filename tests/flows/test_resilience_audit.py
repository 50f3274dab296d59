"""Surviving failures and proving what happened: kill -9 in the middle of meshing, corrupted
cached artefacts, and the tamper-evident audit trail (real flows on the ``ci`` sample)."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from data_catalog.audit import GENESIS, TRAIL, read_trail, verify_trail
from data_catalog.hashing import sha256_file
from flows.stages import STAGE_NAMES, needed_for
from flows.stages.outputs import MERGED
from tests.flows.cli import run_cli, weldrecon
from tests.flows.samples import QUICK_CONFIG, as_published

REPO = Path(__file__).resolve().parents[2]
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")


def _flip_byte(path: Path, offset: int = 40) -> None:
    data = bytearray(path.read_bytes())
    data[min(offset, len(data) - 1)] ^= 0xFF
    path.write_bytes(bytes(data))


@pytest.fixture()
def run_copy(six_run, tmp_path):
    """A private copy of a reconstructed run folder (the ci subset), free to tamper with."""
    out, report = six_run
    copy = tmp_path / "run"
    shutil.copytree(out, copy)
    return copy, report


def _merged_chunk(run: Path, report) -> Path:
    """A data chunk of the merged cloud, in ``run`` (a copy of the reported run folder)."""
    ref = report["refs"]["merge"]
    store = run / Path(ref.file(MERGED.name)).relative_to(Path(ref.path).parents[2])
    return next(p for p in sorted(store.rglob("*")) if p.is_file() and p.name != "zarr.json")


def _stl(run: Path, report) -> Path:
    return run / "results" / f"{report['sample_id']}.stl"


def test_an_untouched_run_verifies(run_copy):
    run, _ = run_copy
    assert verify_trail(run) == []
    done = run_cli("audit", "verify", str(run))
    assert done.returncode == 0, done.stdout + done.stderr
    assert "audit trail intact" in done.stdout


def test_the_trail_says_who_started_the_run_and_every_stage(run_copy):
    run, report = run_copy
    entries = read_trail(run)
    started = entries[0]
    assert started["kind"] == "run-started" and started["started_by"] == "pytest"
    assert len(started["flow_run_id"]) == 36  # the Prefect flow run id
    stages = [e for e in entries if e["kind"] == "stage"]
    assert {e["stage"] for e in stages} == set(STAGE_NAMES)
    assert all(e["record"]["outputs"] and e["task_run_id"] for e in stages)
    assert any(e["kind"] == "run-finished" for e in entries)
    shown = run_cli("audit", "show", str(run))
    assert shown.returncode == 0
    assert "run-started" in shown.stdout and "by pytest" in shown.stdout and "refine" in shown.stdout


@pytest.mark.parametrize("victim", ["chunk", "stl", "record"])
def test_a_changed_artefact_is_named(run_copy, victim):
    run, report = run_copy
    if victim == "chunk":
        target = _merged_chunk(run, report)
    elif victim == "stl":
        target = _stl(run, report)
    else:
        target = run / "stages" / "registration" / Path(report["stage_paths"]["registration"]).name / "record.json"
    _flip_byte(target)
    problems = verify_trail(run)
    assert problems, "a flipped byte went unnoticed"
    named = str(target.relative_to(run))
    artefact = named if victim != "chunk" else str(Path(*target.relative_to(run).parts[:4]))
    assert any(p.where == artefact for p in problems), [str(p) for p in problems]
    done = run_cli("audit", "verify", str(run))
    assert done.returncode == 1 and artefact in done.stdout and "content changed" in done.stdout


def test_an_edited_provenance_record_breaks_the_chain_where_it_was_edited(run_copy):
    run, _ = run_copy
    lines = (run / TRAIL).read_text().splitlines()
    k = next(i for i, line in enumerate(lines) if json.loads(line)["kind"] == "stage"
             and json.loads(line)["stage"] == "registration")
    entry = json.loads(lines[k])
    entry["record"]["metrics"]["residual_max_mm"] = 0.001  # a nicer figure, hash left as it was
    lines[k] = json.dumps(entry, sort_keys=True)
    (run / TRAIL).write_text("\n".join(lines) + "\n")
    problems = verify_trail(run, artefacts=False)
    assert [p.where for p in problems] == [f"trail line {k + 1} (seq {k}, stage)"]
    assert "edited" in problems[0].what
    # dropping a line instead: the next line no longer chains
    del lines[k]
    (run / TRAIL).write_text("\n".join(lines) + "\n")
    problems = verify_trail(run, artefacts=False)
    assert problems and problems[0].where.startswith(f"trail line {k + 1} ")
    done = run_cli("audit", "verify", str(run))
    assert done.returncode == 1 and f"trail line {k + 1}" in done.stdout


def test_a_corrupted_cached_stage_is_recomputed_not_trusted(run_copy, six_sample):
    from flows.reconstruct import reconstruct_sample

    run, report = run_copy
    _flip_byte(_merged_chunk(run, report))
    again = as_published(reconstruct_sample(str(six_sample), str(run), QUICK_CONFIG, started_by="pytest"))
    assert again["cached"]["merge"] is False  # recomputed
    assert again["cached"]["registration"] is True and again["cached"]["refine"] is True
    assert again["stage_keys"]["merge"] == report["stage_keys"]["merge"]  # same inputs, same key
    assert again["outputs"][f"{report['sample_id']}.stl"]["sha256"] == \
        report["outputs"][f"{report['sample_id']}.stl"]["sha256"]
    set_aside = list((run / "stages" / "merge").glob(".corrupt-*"))
    assert len(set_aside) == 1
    recomputed = [e for e in read_trail(run) if e["kind"] == "stage-recomputed"]
    assert len(recomputed) == 1 and MERGED.name in recomputed[0]["reason"]
    assert verify_trail(run) == []  # the recomputed outputs match what the trail recorded


def test_kill_9_while_meshing_then_rerun_gives_identical_outputs(six_run, six_sample, tmp_path, no_stage_cache):
    """Killed (SIGKILL, the whole process group) inside the Poisson reconstruction, the run folder
    is rerun: the rerun sweeps the half-built mesh, makes the mesh and what reads it, and every
    stage's outputs are the uninterrupted run's bytes. Both runs stop after the STL (``export``):
    the stages after it (FE model, reports) are made as in any run, which the session's other runs
    test."""
    from flows.reconstruct import reconstruct_sample

    _, report = six_run
    run = tmp_path / "killed"
    # the stages before the mesh already made in this folder, as by a run with other mesh settings
    # (no shared stage cache here: the mesh is made, and killed, in this folder)
    for stage in [s.name for s in needed_for("export") if s.name not in ("mesh", "export")]:
        shutil.copytree(six_run[0] / "stages" / stage, run / "stages" / stage)
    env = dict(os.environ, PREFECT_SERVER_ANALYTICS_ENABLED="false")
    proc = subprocess.Popen([sys.executable, "-m", "flows.cli", "reconstruct", str(six_sample), "--config", QUICK_CONFIG,
                             "--out", str(run), "--stop-after", "export"], cwd=REPO, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.monotonic() + 300
    try:
        while not list((run / "stages" / "mesh").glob(".build-*")):
            assert proc.poll() is None, "the run ended before meshing started"
            assert time.monotonic() < deadline, "meshing never started"
            time.sleep(0.05)
        time.sleep(0.5)  # well inside the Poisson reconstruction
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    assert not list((run / "stages" / "mesh").glob("*/record.json"))  # meshing did not finish
    assert not (run / "results").exists()
    left = list((run / "stages" / "mesh").glob(".build-*"))
    assert left  # the killed run's half-built mesh
    again = as_published(reconstruct_sample(str(six_sample), str(run), QUICK_CONFIG, started_by="pytest",
                                            stop_after="export"))
    stl = f"{report['sample_id']}.stl"
    made = again["refs"]["export"]  # its mesh.stl is what a finished run publishes as SAMPLE.stl
    assert made.outputs["mesh.stl"] == report["refs"]["export"].outputs["mesh.stl"] == report["outputs"][stl]["sha256"]
    assert sha256_file(Path(made.path) / "mesh.stl") == report["outputs"][stl]["sha256"]
    keys = {n: [x.key for x in r] if isinstance(r, list) else r.key for n, r in again["refs"].items()}
    assert keys == {n: report["stage_keys"][n] for n in keys}
    # the rerun swept what the dead run left half written, and said so in the trail
    assert not any(p.exists() for p in left) and not list(run.rglob(".scratch-*"))
    swept = [e for e in read_trail(run) if e["kind"] == "leftovers-swept"]
    assert len(swept) == 1 and all(p.startswith("stages/") for p in swept[0]["paths"])
    # every stage's outputs, those of the killed run and those rerun, are the uninterrupted run's bytes
    reference = read_trail(six_run[0])
    reference = reference[:next(i for i, e in enumerate(reference) if e["kind"] == "run-finished")]
    expected = {(e["stage"], e.get("item")): e["record"]["outputs"] for e in reference if e["kind"] == "stage"}
    produced = {(e["stage"], e.get("item")): e["record"]["outputs"] for e in read_trail(run) if e["kind"] == "stage"}
    assert {stage for stage, _ in produced} == {s.name for s in needed_for("export")}
    assert [k for k in produced if produced[k] != expected[k]] == []
    ran = {k for k, cached in again["cached"].items() if not cached}
    assert ran == {"mesh", "export"}  # the finished stages were not rerun
    entries = read_trail(run)
    assert [e["kind"] for e in entries].count("run-started") == 2
    assert verify_trail(run) == []


def test_a_run_folder_whose_trail_was_cut_short_reruns_and_records_the_damage(run_copy, six_sample):
    """A write cut short (a crash, a full disk) left half a line at the trail's end: the next run
    of the folder sets it aside with a record of it and finishes; the trail verifies."""
    run, report = run_copy
    half = b'{"kind": "stage", "seq": 9'
    with open(run / TRAIL, "ab") as f:
        f.write(half)
    done = run_cli("audit", "verify", str(run))
    assert done.returncode != 0 and "no line end (the write was cut short)" in done.stdout + done.stderr
    again = weldrecon("reconstruct", str(six_sample), "--out", str(run), "--config", QUICK_CONFIG)
    assert again.returncode == 0, again.stderr[-2000:]
    entries = read_trail(run)
    aside = [e for e in entries if e["kind"] == "trail-damage-set-aside"]
    assert len(aside) == 1 and (run / aside[0]["kept_at"]).read_bytes() == half
    assert entries[-1]["kind"] == "run-finished"
    assert verify_trail(run) == []


@pytest.mark.parametrize("keep", [0, 1, -1, -3])
def test_a_shortened_or_emptied_trail_fails_verification(run_copy, keep):
    """Deleting the trail's last line(s) or all of it leaves results and stage folders that no
    entry records: verify names them."""
    run, report = run_copy
    lines = (run / TRAIL).read_bytes().splitlines(keepends=True)
    (run / TRAIL).write_bytes(b"".join(lines[:keep]))
    problems = [str(p) for p in verify_trail(run)]
    assert problems
    if keep != 0:  # the last run lost its end (earlier runs of the folder may have recorded the same results)
        assert any("the last run has no run-finished, run-failed or run-stopped entry" in p for p in problems), problems
    if keep in (0, 1):
        assert any(p.startswith("stages/merge/") and "no trail entry records" in p for p in problems)
    done = run_cli("audit", "verify", str(run))
    assert done.returncode == 1 and "NOT intact" in done.stdout


def test_audit_on_a_wrong_path_says_so_and_creates_nothing(tmp_path):
    done = subprocess.run([sys.executable, "-m", "flows.cli", "audit", "verify", "no-such-run"], cwd=tmp_path,
                          capture_output=True, text=True, env=dict(os.environ, PYTHONPATH=str(REPO)), timeout=120)
    assert done.returncode == 2
    assert done.stderr.strip() == ("weldrecon audit: error: no-such-run: not a run folder, and no catalog at "
                                   "workspace/catalog.sqlite to look it up in as a sample id (--workspace)")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("how", ["metrics", "output"])
def test_a_cached_stage_tampered_with_its_hashes_is_named_and_a_rerun_does_not_launder_it(run_copy, six_sample, how):
    """A cached stage edited by hand together with the hashes in its record (its metrics, or an
    output replaced and its recorded hash refreshed) is self-consistent: ``audit verify`` names it
    against the trail, and the next run recomputes it instead of publishing it."""
    from data_catalog.hashing import sha256_tree
    from data_catalog.stages import RECORD_NAME

    run, report = run_copy
    folder = run / "stages" / "registration" / report["stage_keys"]["registration"]
    record = json.loads((folder / RECORD_NAME).read_text())
    if how == "metrics":
        record["metrics"]["residual_max_mm"] = 0.001  # a nicer figure
    else:
        summary = folder / "registration.json"
        body = json.loads(summary.read_text())
        body["pairs_below_min_common"] = []
        summary.write_text(json.dumps(body))
        record["outputs"]["registration.json"] = sha256_tree(summary)
    (folder / RECORD_NAME).write_text(json.dumps(record))
    before = [str(p) for p in verify_trail(run)]
    assert any(p.startswith(f"stages/registration/{folder.name}/") and "content changed" in p for p in before)
    again = weldrecon("reconstruct", str(six_sample), "--out", str(run), "--config", QUICK_CONFIG)
    assert again.returncode == 0, again.stderr[-2000:]
    entries = read_trail(run)
    redone = [e for e in entries if e["kind"] == "stage-recomputed" and e["stage"] == "registration"]
    assert len(redone) == 1 and "do not match the audit trail" in redone[0]["reason"]
    last = [e for e in entries if e["kind"] == "stage" and e["stage"] == "registration"][-1]
    assert last["cached"] is False and last["record"]["metrics"]["residual_max_mm"] != 0.001
    assert list((run / "stages" / "registration").glob(".tampered-*"))
    assert verify_trail(run) == []
    published = json.loads((run / "results" / "report.json").read_text())
    assert published["stages"]["registration"]["residual_max_mm"] != 0.001
    # what the run did about it is said on the terminal, and verify names it (intact is not uneventful)
    said = [line for line in again.stderr.splitlines() if "registration: cached outputs do not match the audit trail" in line]
    assert len(said) == 1 and "set aside to .tampered-" in said[0] and "recomputed" in said[0], again.stderr[-2000:]
    verified = weldrecon("audit", "verify", str(run))
    assert verified.returncode == 0
    head, *events = verified.stdout.splitlines()
    assert head.startswith(f"{run}: audit trail intact: ") and head.endswith("; 1 event recorded:"), verified.stdout
    assert len(events) == 1 and f"seq {redone[0]['seq']} " in events[0] and \
        "stage registration recomputed: cached outputs do not match the audit trail" in events[0]


def _children(pid: int) -> set[int]:
    out: set[int] = set()
    for task in Path(f"/proc/{pid}/task").iterdir():
        out |= {int(c) for c in (task / "children").read_text().split()}
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, IndexError):
        return False
    return state != "Z"


def test_a_run_killed_alone_leaves_no_server_behind(six_sample, tmp_path):
    """The out-of-memory killer kills one process, not its group: the run's temporary Prefect API
    server (uvicorn, a child) must go with it."""
    run = tmp_path / "killed"
    env = dict(os.environ, PREFECT_SERVER_ANALYTICS_ENABLED="false")
    env.pop("PREFECT_API_URL", None)
    proc = subprocess.Popen([sys.executable, "-m", "flows.cli", "reconstruct", str(six_sample), "--config", QUICK_CONFIG,
                             "--out", str(run)], cwd=REPO, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.monotonic() + 300
    try:
        while not (run / TRAIL).is_file():  # the flow runs: its API server is up
            assert proc.poll() is None, "the run ended before it started"
            assert time.monotonic() < deadline, "the run never started"
            time.sleep(0.1)
        servers = {c for c in _children(proc.pid)
                   if b"uvicorn" in Path(f"/proc/{c}/cmdline").read_bytes()}
        assert len(servers) == 1, f"{len(servers)} API servers among the run's children, expected its own one"
        os.kill(proc.pid, signal.SIGKILL)  # this process alone
        proc.wait()
        gone_by = time.monotonic() + 30
        while any(_alive(s) for s in servers) and time.monotonic() < gone_by:
            time.sleep(0.2)
        assert not any(_alive(s) for s in servers), "the API server outlived the run"
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)


def test_a_rerun_does_not_make_a_cut_trail_whole_again(run_copy, six_sample):
    """The trail cut back to just before the first run's run-finished entry (later tests may have
    run the shared folder again), then the folder run again: the rerun records what it found (the
    results no entry records, the head the catalog kept is gone) before appending, and ``audit
    verify`` names that from then on."""
    from flows.reconstruct import reconstruct_sample

    run, report = run_copy
    lines = (run / TRAIL).read_bytes().splitlines(keepends=True)
    assert json.loads(lines[report["trail_head"]["seq"]])["hash"] == report["trail_head"]["hash"]
    (run / TRAIL).write_bytes(b"".join(lines[:report["trail_head"]["seq"]]))
    again = as_published(reconstruct_sample(str(six_sample), str(run), QUICK_CONFIG, started_by="pytest",
                                            trail_head=report["trail_head"]["hash"]))
    # the folder's stages are not trusted (its trail did not verify): set aside, copied again from
    # the session's stage cache, each saying so
    assert all(again["cached"].values())
    redone = [e for e in read_trail(run) if e["kind"] == "stage-recomputed"]
    assert redone and all("the folder's audit trail did not verify when the run started" in e["reason"]
                          and e["reason"].endswith("copied again from the stage cache") for e in redone)
    found = [e for e in read_trail(run) if e["kind"] == "trail-problems-found"]
    assert len(found) == 1
    assert any("no run-finished entry records this result" in p for p in found[0]["problems"])
    assert any(f"holds no entry with hash {report['trail_head']['hash'][:12]}" in p for p in found[0]["problems"])
    problems = [str(p) for p in verify_trail(run)]  # (stage folders of later runs with other settings: unrecorded too)
    assert any("a run found the trail not intact before it" in p and "no run-finished entry records" in p
               for p in problems), problems
    done = run_cli("audit", "verify", str(run))
    assert done.returncode == 1 and "a run found the trail not intact before it" in done.stdout


def test_a_stage_forged_with_its_trail_rechained_is_not_reused(run_copy, six_sample, tmp_path):
    """A stage's record edited (a nicer registration residual), its trail entry edited to match
    and the chain computed anew: consistent on its own, only the head kept outside tells. The
    rerun finds the trail not intact against that head, so it trusts none of the folder's stages:
    each is set aside and copied again from the session's stage cache (verified there; made again
    where the cache lacks it), and the published report is the untampered run's, byte for byte
    (before: the forged figure went into the report)."""
    from data_catalog.audit import _digest
    from data_catalog.catalog import Catalog

    run, report = run_copy
    published = (run / "results" / "report.json").read_bytes()
    [folder] = (run / "stages" / "registration").iterdir()
    record = json.loads((folder / "record.json").read_text())
    record["metrics"]["residual_max_mm"] = 0.001
    (folder / "record.json").write_text(json.dumps(record, indent=1))
    forged = hashlib.sha256((folder / "record.json").read_bytes()).hexdigest()
    entries, prev = [], GENESIS
    for entry in read_trail(run):
        rel = f"stages/registration/{folder.name}/record.json"
        if rel in (entry.get("artefacts") or {}):
            entry["artefacts"][rel] = forged
            entry["record"]["metrics"]["residual_max_mm"] = 0.001
        entry["seq"], entry["prev"] = len(entries), prev
        entry["hash"] = prev = _digest(entry)
        entries.append(entry)
    (run / TRAIL).write_text("".join(json.dumps(e, sort_keys=True, default=str) + "\n" for e in entries))
    assert verify_trail(run) == []  # consistent on its own
    # the folder catalogued with its head, as a batch leaves it; `weldrecon reconstruct` of that
    # folder holds the trail to the head the workspace's catalog keeps
    workspace = tmp_path / "ws"
    catalog = Catalog(workspace)
    record = catalog.register(six_sample)
    catalog.mark_running(record.sample_id, run)
    catalog.mark_done(record.sample_id, record.fingerprint, {}, trail_head=report["trail_head"])
    done = weldrecon("reconstruct", str(six_sample), "--out", str(run), "--config", QUICK_CONFIG,
                     env={"WELDRECON_WORKSPACE": str(workspace)})
    assert done.returncode == 0, done.stderr
    assert (run / "results" / "report.json").read_bytes() == published
    redone = [e for e in read_trail(run) if e["kind"] == "stage-recomputed"]
    # said on the terminal once, not once a stage, with how many were made again
    said = [line.split("] ", 1)[-1] for line in done.stderr.splitlines() if "untrusted" in line]
    assert said == ["the folder's audit trail did not verify when the run started: each of its stages is set aside "
                    "(.untrusted-*) and recomputed or copied from the stage cache; `weldrecon audit verify` lists them",
                    f"{len(redone)} stage(s) of the folder set aside as untrusted and made again"], done.stderr
    assert {e["stage"] for e in redone} >= {"registration", "report"}
    assert all(e["reason"].endswith("copied again from the stage cache") for e in redone)
    assert [p.name.split("-")[0] for p in (run / "stages" / "registration").iterdir() if p.name.startswith(".")] == [
        ".untrusted"]
