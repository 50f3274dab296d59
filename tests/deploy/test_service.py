"""The scheduled service for real: deploy/service.sh starts a Prefect server on loopback, the
process work pool, the deployments of deploy/prefect.yaml and a worker; the on-demand
deployment is triggered on the six-pass ``ci`` subset and must complete through the worker, making
every stage. The session's own run of the subset (``six_run``) is made first: the deployment's run
then copies its stages from the session's stage cache (the service's plumbing, not the
reconstruction, is what this test runs; made here too, the stages cost a minute of CPU twice)."""

from __future__ import annotations

import json
import os
import socket
import subprocess
from pathlib import Path

import pytest

from data_catalog.audit import read_trail, verify_trail
from flows.stages import STAGE_NAMES
from tests.flows.samples import QUICK_CONFIG

REPO = Path(__file__).resolve().parents[2]
PREFECT = REPO / ".venv" / "bin" / "prefect"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_server_worker_and_deployments_on_loopback(six_sample, six_run, tmp_path):
    if not PREFECT.exists():
        pytest.fail(f"{PREFECT} is missing: run `make setup` first")
    port = _free_port()
    env = dict(os.environ, WELDRECON_WORKSPACE=str(tmp_path / "ws"), WELDRECON_SAMPLES=str(tmp_path / "samples"),
               WELDRECON_PORT=str(port), PREFECT_WORKER_QUERY_SECONDS="2")
    for key in ("PREFECT_API_URL", "PREFECT_HOME"):
        env.pop(key, None)
    service = [str(REPO / "deploy" / "service.sh")]
    pids = {}
    try:
        up = subprocess.run([*service, "up"], env=env, cwd=REPO, capture_output=True, text=True, timeout=300)
        assert up.returncode == 0, up.stdout[-3000:] + up.stderr[-3000:]
        pids = {name: int((tmp_path / "ws" / "service" / f"{name}.pid").read_text()) for name in ("server", "worker")}
        env.update(PREFECT_HOME=str(tmp_path / "ws" / "service" / "prefect"),
                   PREFECT_API_URL=f"http://127.0.0.1:{port}/api")
        nightly = subprocess.run([str(PREFECT), "deployment", "inspect", "reconstruct-batch/nightly"], env=env,
                                 capture_output=True, text=True, timeout=60)
        assert nightly.returncode == 0 and "0 2 * * *" in nightly.stdout, nightly.stdout + nightly.stderr
        out = tmp_path / "ws" / "runs" / "ci"
        run = subprocess.run([str(PREFECT), "deployment", "run", "reconstruct-sample/on-demand",
                              "--param", f"sample_dir={six_sample}", "--param", f"out_dir={out}",
                              "--param", f"config_path={QUICK_CONFIG}", "--watch",
                              "--watch-timeout", "400"], env=env, capture_output=True, text=True, timeout=480)
        assert run.returncode == 0 and "Completed" in run.stdout, run.stdout[-3000:] + run.stderr[-3000:]
        report = json.loads((out / "results" / "report.json").read_text())
        assert report["mesh"]["triangles"] > 10_000
        assert set(report["stage_keys"]) == set(STAGE_NAMES) - {"report", "qa_report"}  # what the report reads
        started = read_trail(out)[0]
        assert started["started_by"] == "deployment" and started["deployment_name"] == "on-demand"
        assert verify_trail(out) == []
        worker_log = (tmp_path / "ws" / "service" / "worker.log").read_text()
        assert "Completed" in worker_log or "completed" in worker_log.lower()
    finally:
        down = subprocess.run([*service, "down"], env=env, cwd=REPO, capture_output=True, text=True, timeout=60)
        assert down.returncode == 0, down.stderr
        for name, pid in pids.items():  # nothing left running
            assert not Path(f"/proc/{pid}").exists() or "zombie" in Path(f"/proc/{pid}/status").read_text(), name
