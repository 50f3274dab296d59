"""Running the ``weldrecon`` command line the way a user does: a separate process."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def cli_env(**added: str) -> dict[str, str]:
    """The environment a command the tests start runs in: this process's as it is now (the
    session's Prefect API and stage cache are set after the tests are collected), quiet, with
    ``added``."""
    return dict(os.environ, PREFECT_SERVER_ANALYTICS_ENABLED="false", PREFECT_LOGGING_LEVEL="WARNING", **added)


def run_cli(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """``python -m flows.cli ARGS`` from the repository root, output captured (``env``: variables
    added to this process's)."""
    return subprocess.run([sys.executable, "-m", "flows.cli", *args], capture_output=True, text=True, cwd=REPO,
                          env=cli_env(**(env or {})), timeout=600)
