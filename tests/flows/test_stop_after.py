"""``weldrecon reconstruct --stop-after STAGE``: the stages up to STAGE and no further, nothing
published, the trail intact and ended by ``run-stopped``; a later full run reuses what was made."""

from __future__ import annotations

from pathlib import Path

from data_catalog.audit import read_trail
from tests.conftest import SIX
from tests.flows.cli import run_cli, weldrecon
from tests.flows.samples import QUICK_CONFIG, copy_sample

REPO = Path(__file__).resolve().parents[2]


def test_a_run_stopped_after_a_stage_makes_only_the_stages_before_it(ci_sample, tmp_path):
    sample = copy_sample(ci_sample, tmp_path / "s", SIX)
    run = tmp_path / "run"
    done = weldrecon("reconstruct", str(sample), "--out", str(run), "--config", QUICK_CONFIG, "--stop-after", "refine")
    assert done.returncode == 0, done.stderr
    assert "stopped after stage refine: denoise (" in done.stdout and f"nothing published in {run}" in done.stdout
    assert sorted(p.name for p in (run / "stages").iterdir()) == ["denoise", "refine", "registration", "targets"]
    assert not (run / "results").exists()
    trail = read_trail(run)
    assert trail[-1]["kind"] == "run-stopped" and trail[-1]["after"] == "refine"
    verify = run_cli("audit", "verify", str(run))
    assert verify.returncode == 0 and "audit trail intact" in verify.stdout  # a stopped run is an ended one
    again = weldrecon("reconstruct", str(sample), "--out", str(run), "--config", QUICK_CONFIG, "--stop-after", "merge")
    assert again.returncode == 0, again.stderr
    entries = read_trail(run)
    last = max(k for k, e in enumerate(entries) if e["kind"] == "run-started")
    made = {(e["stage"], e.get("item")): e["cached"] for e in entries[last:] if e["kind"] == "stage"}
    assert all(cached for (stage, _), cached in made.items() if stage != "merge")  # made before, in this folder
    assert ("merge", None) in made


def test_an_unknown_stage_is_refused_before_any_work(ci_sample, tmp_path):
    done = run_cli("reconstruct", str(ci_sample), "--out", str(tmp_path / "run"), "--stop-after", "meshing")
    assert done.returncode == 2
    assert done.stderr.strip().splitlines()[-1].startswith(
        "weldrecon reconstruct: error: --stop-after meshing: no such stage; the stages are denoise, targets, ")
    assert not (tmp_path / "run").exists()
