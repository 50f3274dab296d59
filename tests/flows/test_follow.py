"""Streaming: ``weldrecon simulate --pace`` writes the plan first and each pass when the robot
would have finished it; ``weldrecon reconstruct --follow`` starts each pass's stages as soon as it
lands, so the robot and the reconstruction overlap, and ends with the same mesh as a run on the
finished sample."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import time
from datetime import datetime
from pathlib import Path

import pytest

from data_catalog.audit import read_trail
from tests.flows.cli import REPO, run_cli


@pytest.mark.slow
def test_follow_a_paced_scan_overlaps_it_and_gives_the_same_mesh(ci_run, tmp_path):
    _, finished = ci_run
    sample, out = tmp_path / "live", tmp_path / "run"
    env = dict(os.environ, PREFECT_SERVER_ANALYTICS_ENABLED="false", PREFECT_LOGGING_LEVEL="WARNING")
    # the ci plan scans for ~3.5 min; at x12 its passes land over ~18 s
    scan = subprocess.Popen([sys.executable, "-m", "flows.cli", "simulate", "--preset", "ci", "--no-preview",
                             "--pace", "x12", str(sample)], cwd=REPO, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        follow = run_cli("reconstruct", str(sample), "--out", str(out), "--follow", "--follow-timeout", "120",
                         "--config", str(REPO / "deploy" / "configs" / "ci.yaml"))
    finally:
        _, scan_err = scan.communicate(timeout=300)
    assert scan.returncode == 0, scan_err[-2000:]
    assert follow.returncode == 0, follow.stderr[-3000:]
    assert scan_err.count("passes land at 12 x") == 1
    # the first passes were denoised while the robot was still scanning: their stage records
    # finished before the simulation wrote its last pass
    trail = read_trail(out)
    denoised = sorted(datetime.fromisoformat(e["record"]["finished"]).timestamp() for e in trail
                      if e.get("kind") == "stage" and e.get("stage") == "denoise")
    assert len(denoised) == 14
    last_pass_landed = (sample / "passes").stat().st_mtime  # the last rename into passes/
    assert denoised[0] < last_pass_landed - 2.0, (denoised[0], last_pass_landed)
    # the same mesh as the run on the finished sample (the manifest of a paced scan has no content
    # hashes; the stages do not read them)
    digest = lambda p: hashlib.sha256(Path(p).read_bytes()).hexdigest()  # noqa: E731
    stl_live = out / "results" / f"{finished['sample_id']}.stl"
    stl_done = Path(finished["outputs"][f"{finished['sample_id']}.stl"]["path"])
    assert digest(stl_live) == digest(stl_done)


def test_follow_names_the_pass_that_never_lands(ci_sample, tmp_path):
    import shutil

    sample = tmp_path / "partial"
    shutil.copytree(ci_sample, sample)
    missing = sorted((sample / "passes").iterdir())[-1]
    shutil.rmtree(missing)
    started = time.monotonic()
    done = run_cli("reconstruct", str(sample), "--out", str(tmp_path / "run"), "--follow", "--follow-timeout", "3",
                   "--config", str(REPO / "deploy" / "configs" / "ci.yaml"))
    assert done.returncode == 2
    assert f"{missing.name} did not appear (complete) within 3 s" in done.stderr, done.stderr[-2000:]
    assert time.monotonic() - started < 300
