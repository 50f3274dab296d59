"""Shared fixtures: the ``ci`` sample is simulated once per test session."""

from __future__ import annotations

from pathlib import Path

import pytest

from simulator.presets import preset_config

CI_CONFIG = Path(__file__).resolve().parents[1] / "deploy" / "configs" / "ci.yaml"
from simulator.run import simulate


@pytest.fixture(scope="session", autouse=True)
def _traceback_logs_in_a_temporary_folder(tmp_path_factory):
    """The command line's traceback logs (flows.cli) go under the session's temporary folder."""
    import os

    os.environ["WELDRECON_LOG_DIR"] = str(tmp_path_factory.mktemp("logs"))


@pytest.fixture(scope="session")
def ci_sample(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ci") / "sample"
    simulate(preset_config("ci"), out)
    return out


@pytest.fixture(scope="session")
def ci_config():
    return preset_config("ci")


@pytest.fixture(scope="session")
def ci_run(ci_sample, tmp_path_factory):
    """The ``ci`` sample reconstructed once (real Prefect engine, ci settings): (run folder, report)."""
    import os

    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    from flows.reconstruct import reconstruct_sample

    out = tmp_path_factory.mktemp("recon") / "run"
    report = reconstruct_sample(str(ci_sample), str(out), str(CI_CONFIG), started_by="pytest")
    return out, report


@pytest.fixture(scope="session", autouse=True)
def _stop_prefects_temporary_server():
    """Flows run in this process start Prefect's temporary API server; stop it while pytest's
    output is still open (at interpreter exit its goodbye line met a closed stream)."""
    yield
    import contextlib

    from prefect.logging.handlers import APILogHandler
    from prefect.server.api.server import SubprocessASGIServer

    with contextlib.suppress(Exception):  # the last log lines while the server still listens
        APILogHandler().flush()
    SubprocessASGIServer().stop()  # the one instance Prefect started (a fresh one stops nothing)
