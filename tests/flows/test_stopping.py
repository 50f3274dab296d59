"""A run told to stop (SIGTERM, SIGINT) stops at once with every process it started, says so in
one line, publishes nothing half-written, and the next run of the folder goes on from the stages
that finished (issue 28: SIGTERM did not stop the run; its meshing child was retried). The signal
is sent while gmsh meshes the volume, to the command's process alone: the gmsh child must end too."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil

from tests.conftest import SIX
from tests.flows.cli import REPO, cli_env, run_cli
from tests.flows.samples import copy_sample

CI_CONFIG = str(REPO / "deploy" / "configs" / "ci.yaml")


def _stages_done(run: Path) -> set[str]:
    trail = run / "audit" / "trail.jsonl"
    if not trail.is_file():
        return set()
    return {e.get("stage") for e in map(json.loads, trail.read_text().splitlines()) if e.get("kind") == "stage"}


def test_a_signal_stops_the_run_and_its_children_at_once(ci_sample, tmp_path):
    """SIGTERM here; SIGINT and SIGHUP take the same handler (``flows.stopping``)."""
    signum = signal.SIGTERM
    sample = copy_sample(ci_sample, tmp_path / "s", SIX)
    run = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "flows.cli", "reconstruct", str(sample), "--out", str(run),
                             "--config", CI_CONFIG], cwd=REPO, env=cli_env(), stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline, children = time.monotonic() + 300, []
        while not any("gmsh_volume" in " ".join(c.cmdline()) for c in children):  # the volume stage's gmsh child
            assert proc.poll() is None and time.monotonic() < deadline, "the run ended before its volume stage"
            time.sleep(0.1)
            try:
                children = psutil.Process(proc.pid).children(recursive=True)
            except psutil.Error:
                children = []
        proc.send_signal(signum)  # to the command's process alone, not its group
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + signum
    assert err.splitlines()[-1] == (f"weldrecon reconstruct: stopped by {signal.Signals(signum).name}; its child "
                                    "processes ended, nothing it was writing was published"), err
    assert not any(c.is_running() and c.status() != psutil.STATUS_ZOMBIE for c in children)
    assert not (run / "results").exists()
    assert "volume" not in _stages_done(run)
    done = run_cli("reconstruct", str(sample), "--out", str(run), "--config", CI_CONFIG, "--stop-after", "export")
    assert done.returncode == 0, done.stderr
    computed = [line for line in done.stderr.splitlines() if " done " in line and "cached" not in line]
    assert "mesh done cached" in done.stderr, computed  # the stages before volume finished and are kept
