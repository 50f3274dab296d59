"""A run told to stop (SIGTERM; SIGINT and SIGHUP take the same handler, ``flows.stopping``)
stops at once with every process it started, says so in one line and publishes nothing (issue 28:
SIGTERM did not stop the run; its meshing child was retried).

The run here starts its own Prefect API server (a plain ``weldrecon reconstruct`` does: the
tests' session server is not given to it), so it has a child process from its first seconds;
the signal goes to the command's process alone, not its group: the child must end too. (By
hand, 2026-11-27: SIGTERM to the process group during the volume stage had left the command
running on, its gmsh child killed; with ``flows.stopping`` the command, gmsh and the server end
within a second.)"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil

from tests.conftest import SIX
from tests.flows.cli import REPO, cli_env
from tests.flows.samples import QUICK_CONFIG, copy_sample



def _started(run: Path) -> bool:
    trail = run / "audit" / "trail.jsonl"
    return trail.is_file() and any(json.loads(line).get("kind") == "run-started"
                                   for line in trail.read_text().splitlines() if line.strip())


def test_sigterm_stops_the_run_and_its_children_at_once(ci_sample, tmp_path):
    sample = copy_sample(ci_sample, tmp_path / "s", SIX)
    run = tmp_path / "run"
    env = {k: v for k, v in cli_env().items() if k != "PREFECT_API_URL"}  # the run starts its own server
    proc = subprocess.Popen([sys.executable, "-m", "flows.cli", "reconstruct", str(sample), "--out", str(run),
                             "--config", QUICK_CONFIG], cwd=REPO, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline, children = time.monotonic() + 120, []
        while not (children and _started(run)):  # its server up and the run begun
            assert proc.poll() is None and time.monotonic() < deadline, "the run ended before it could be stopped"
            time.sleep(0.05)
            try:
                children = psutil.Process(proc.pid).children(recursive=True)
            except psutil.Error:
                children = []
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM, err[-2000:]
    assert err.splitlines()[-1] == ("weldrecon reconstruct: stopped by SIGTERM; its child processes ended, nothing "
                                    "it was writing was published"), err[-2000:]
    assert not any(c.is_running() and c.status() != psutil.STATUS_ZOMBIE for c in children)
    assert not (run / "results").exists()
    # (a rerun of a folder whose run was killed: tests/flows/test_resilience_audit.py)
