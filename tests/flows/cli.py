"""Running the ``weldrecon`` command line: as a user does, in a process of its own (``run_cli``),
or in this test process (``weldrecon``), for the commands whose own work is what a test is about.

A command in a process of its own pays ~5 s of imports (Prefect, the compute stack) before its
first line of work; in this process they are made once per test worker. What differs in a
process of its own (the exit status through ``sys.exit``, a closed pipe, a kill, what loads
before a refusal) is tested there."""

from __future__ import annotations

import contextlib
import io
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


def weldrecon(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """``weldrecon ARGS`` run in this process (``flows.cli.main``), what it wrote to stdout and
    stderr captured, as ``run_cli`` gives it: the exit status, the text. The environment
    (``env`` added) and this process's logging are as before afterwards."""
    from prefect.logging.configuration import ensure_logging_setup

    from flows.cli import main

    ensure_logging_setup()  # Prefect's logging, configured once a process by what uses Prefect first
    saved, logging_before = dict(os.environ), _logging_state()
    out, err = io.StringIO(), io.StringIO()
    try:
        os.environ.update(cli_env(**(env or {})))
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = main(list(args))
            except SystemExit as exc:  # argparse's refusal of a malformed command line
                code = exc.code if isinstance(exc.code, int) else 2
    finally:
        os.environ.clear()
        os.environ.update(saved)
    after = _logging_state()
    changed = [name for name, handlers in logging_before[0].items() if after[0].get(name) != handlers]
    assert not changed and after[1] == logging_before[1], (f"weldrecon {' '.join(args)} left this process's logging "
                                                           f"changed: {changed or 'warnings.showwarning'}")
    return subprocess.CompletedProcess(["weldrecon", *args], code, out.getvalue(), err.getvalue())


def _logging_state() -> tuple:
    """Every logger's handlers and level, and where warnings go (what a command may change; a
    logger it made is not compared). A Dask nanny left to the garbage collector takes its handler
    off ``distributed.nanny`` when it is collected (``weakref.finalize``), which, left to chance,
    happened during a later command: the tests that start Dask clusters collect their garbage as
    they end (tests/conftest.py ``collected_after``), not every command here (a full collection
    twice a command was ~45 s of the suite's CPU)."""
    import logging
    import warnings

    loggers = {"": logging.getLogger(), **{name: lg for name, lg in logging.root.manager.loggerDict.items()
                                            if isinstance(lg, logging.Logger)}}
    return ({name: (list(lg.handlers), lg.level) for name, lg in sorted(loggers.items()) if lg.handlers},
            warnings.showwarning)
