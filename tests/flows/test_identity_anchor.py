"""Whose run folder is it, and is its trail the one that was written: a renamed sample or a
reused folder never replaces another sample's results, and a trail cut back or rewritten fails
verification against the head kept outside the folder (the catalog, or a noted ``--head``)."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import pytest

from data_catalog.audit import GENESIS, TRAIL, read_trail, verify_trail
from data_catalog.catalog import Catalog
from data_catalog.hashing import sha256_tree
from tests.flows.cli import run_cli

REPO = Path(__file__).resolve().parents[2]
CI_CONFIG = str(REPO / "deploy" / "configs" / "ci.yaml")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")


def _sample(ci_sample: Path, dst: Path, sample_id: str) -> Path:
    """A copy of the ci sample (manifest and passes) with another sample id."""
    dst.mkdir(parents=True)
    shutil.copytree(ci_sample / "passes", dst / "passes")
    shutil.copyfile(ci_sample / "manifest.json", dst / "manifest.json")
    _rename(dst, sample_id)
    return dst


def _rename(sample: Path, sample_id: str) -> None:
    manifest = json.loads((sample / "manifest.json").read_text())
    manifest["sample_id"] = sample_id
    (sample / "manifest.json").write_text(json.dumps(manifest))


def _snapshot(folder: Path) -> dict[str, str]:
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture()
def sample_a(ci_sample, tmp_path):
    return _sample(ci_sample, tmp_path / "sample", "ident-a")


def test_the_catalog_never_rebuilds_a_sample_from_a_folder_that_now_holds_another(sample_a, tmp_path):
    catalog = Catalog(tmp_path / "ws")
    first = catalog.register(sample_a)
    catalog.mark_running("ident-a", catalog.out_dir_for("ident-a"))
    catalog.mark_done("ident-a", first.fingerprint, {"ident-a.stl": "0" * 64}, trail_head={"seq": 3, "hash": "f" * 64})
    assert catalog.due() == []

    _rename(sample_a, "ident-b")  # the folder reused for another specimen (or the sample renamed)
    unreadable: dict[str, str] = {}
    due = catalog.due(unreadable=unreadable)
    assert due == [] and "now holds sample ident-b" in unreadable["ident-a"]  # not rebuilt as ident-a
    record = catalog.get("ident-a")
    assert (record.state, record.failed_stage) == ("failed", "register")
    assert record.artefacts == {"ident-a.stl": "0" * 64} and record.trail_head == {"seq": 3, "hash": "f" * 64}

    done = run_cli("catalog", "register", str(sample_a), "--workspace", str(tmp_path / "ws"))  # the folder again
    assert done.returncode == 0 and done.stdout.splitlines() == ["ident-b: new"]
    assert done.stderr.strip().startswith(f"weldrecon catalog: warning: sample ident-a: failed at register: cannot "
                                          f"read the sample folder {sample_a.resolve()}: the folder now holds sample "
                                          "ident-b"), done.stderr
    assert catalog.get("ident-b").state == "new"
    assert "ident-a's run folder and results are kept" in catalog.get("ident-a").error
    assert [r.sample_id for r in catalog.due()] == ["ident-b"]
    shown = run_cli("catalog", "list", "--workspace", str(tmp_path / "ws"))
    assert "ident-a" in shown.stdout and "failed at register" in shown.stdout


def test_a_catalog_from_before_the_trail_head_column_is_upgraded(tmp_path):
    import sqlite3

    workspace = tmp_path / "ws"
    workspace.mkdir()
    with sqlite3.connect(workspace / "catalog.sqlite") as db:  # the schema of the catalogs in use
        db.execute("CREATE TABLE samples (sample_id TEXT PRIMARY KEY, sample_dir TEXT NOT NULL, fingerprint TEXT "
                   "NOT NULL, state TEXT NOT NULL, failed_stage TEXT, error TEXT, out_dir TEXT, done_fingerprint TEXT, "
                   "artefacts TEXT NOT NULL DEFAULT '{}', flow_run_id TEXT, registered TEXT NOT NULL, updated TEXT "
                   "NOT NULL)")
        db.execute("INSERT INTO samples VALUES ('old', '/x', 'f', 'done', NULL, NULL, '/r', 'f', '{}', NULL, 't', 't')")
    record = Catalog(workspace).get("old")
    assert record.state == "done" and record.trail_head is None


def test_the_flow_refuses_a_sample_folder_that_holds_another_sample(sample_a, tmp_path):
    from flows.reconstruct import reconstruct_sample

    out = tmp_path / "run"
    with pytest.raises(ValueError, match="its manifest names sample ident-a, not ident-z"):
        reconstruct_sample(str(sample_a), str(out), CI_CONFIG, started_by="pytest", sample_id="ident-z")
    assert not out.exists()


def test_a_run_folder_of_one_sample_is_refused_to_another(ci_run, ci_sample, tmp_path):
    """A renamed sample (or another sample given the same --out) is refused before anything is
    written: the finished run's folder stays byte for byte."""
    out, report = ci_run
    run = tmp_path / "run"
    shutil.copytree(out, run)
    before = _snapshot(run)
    renamed = _sample(ci_sample, tmp_path / "renamed", "ci-renamed")
    done = run_cli("reconstruct", str(renamed), "--out", str(run), "--config", CI_CONFIG)
    assert done.returncode == 2, done.stdout + done.stderr
    error = done.stderr.strip().splitlines()
    assert len(error) == 1 and f"holds the runs of sample {report['sample_id']}" in error[0]
    assert "not of ci-renamed" in error[0] and "Traceback" not in done.stderr
    assert _snapshot(run) == before


def _rechained(entries: list[dict], edit) -> list[dict]:
    """The trail rewritten by someone who knows the hashing: ``edit`` applied, every hash and
    link computed anew."""
    from data_catalog.audit import _digest

    out, prev = [], GENESIS
    for entry in entries:
        entry = edit(dict(entry))
        if entry is None:
            continue
        entry["seq"], entry["prev"] = len(out), prev
        entry["hash"] = _digest(entry)
        prev = entry["hash"]
        out.append(entry)
    return out


def _write(run: Path, entries: list[dict]) -> None:
    (run / TRAIL).write_text("".join(json.dumps(e, sort_keys=True, default=str) + "\n" for e in entries))


def test_a_rewritten_or_emptied_trail_fails_against_the_head_kept_outside(ci_run, ci_sample, tmp_path):
    out, report = ci_run
    head = report["trail_head"]
    trail = read_trail(out)
    assert trail[head["seq"]]["hash"] == head["hash"] and trail[head["seq"]]["kind"] == "run-finished"
    run = tmp_path / "run"
    shutil.copytree(out, run)
    workspace = tmp_path / "ws"
    catalog = Catalog(workspace)
    record = catalog.register(ci_sample)
    catalog.mark_running(record.sample_id, run)
    catalog.mark_done(record.sample_id, record.fingerprint, {}, trail_head=head)
    done = run_cli("audit", "verify", record.sample_id, "--workspace", str(workspace))
    assert done.returncode == 0 and "holds the head kept by the catalog" in done.stdout, done.stdout + done.stderr

    # laundered: the refine stage's recorded metrics edited and the chain recomputed; on its own
    # the trail is consistent, so only the anchor can tell
    def edit(entry):
        if entry.get("kind") == "stage" and entry.get("stage") == "refine":
            entry["record"] = dict(entry["record"], metrics=dict(entry["record"]["metrics"], edited=True))
        return entry

    _write(run, _rechained(trail, edit))
    assert verify_trail(run) == []
    for target in (record.sample_id, str(run)):  # by sample id, or by the catalogued run folder
        done = run_cli("audit", "verify", target, "--workspace", str(workspace))
        assert done.returncode == 1, done.stdout + done.stderr
        assert f"holds no entry with hash {head['hash'][:12]}" in done.stdout and "the catalog" in done.stdout
    done = run_cli("audit", "verify", str(run), "--head", head["hash"], "--workspace", str(tmp_path / "none"))
    assert done.returncode == 1 and "which --head recorded" in done.stdout

    # emptied, with every stage folder and result gone too: nothing left in the folder to disagree
    (run / TRAIL).write_text("")
    shutil.rmtree(run / "stages")
    shutil.rmtree(run / "results")
    assert verify_trail(run) == []
    done = run_cli("audit", "verify", record.sample_id, "--workspace", str(workspace))
    assert done.returncode == 1 and "holds no entry with hash" in done.stdout
    done = run_cli("audit", "verify", str(run), "--head", "abc", "--workspace", str(tmp_path / "none"))
    assert done.returncode == 2 and "--head abc: expected an entry's sha256 (64 hex digits)" in done.stderr


def test_results_hold_the_settings_they_were_made_with(ci_run):
    """What results/ holds is what the last finished run recorded (the session's ci run folder is
    shared: tests/flows/test_reconstruct_ci.py runs it again, which publishes again, its page
    naming the new trail head)."""
    out, report = ci_run
    results = out / "results"
    settings = json.loads((results / "config.json").read_text())
    assert settings == report["config"]
    assert sorted(p.name for p in results.iterdir()) == sorted(report["outputs"])
    finished = [e for e in read_trail(out) if e["kind"] == "run-finished"][-1]
    assert finished["seq"] >= report["trail_head"]["seq"]
    assert finished["artefacts"] == {f"results/{n}": sha256_tree(results / n) for n in report["outputs"]}
