"""A temporary Prefect API server: Prefect's API app served by uvicorn in a child process, on a free
loopback port, that the kernel stops when the process that started it dies, however it dies
(``prctl(PR_SET_PDEATHSIG)``; Prefect's own temporary server outlived a ``kill -9`` of its parent
for hours). A run of the command line starts one for itself and its Dask workers
(``flows.reconstruct.prefect_api_for_workers``); each test process starts one for itself
(``tests/conftest.py``).

``launch`` returns at once, so that the caller can go on (a test process collects its tests) while
the server starts; ``wait_ready`` waits for its health check. Nothing here imports Prefect."""

from __future__ import annotations

import ctypes
import importlib.util
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Sequence
from pathlib import Path

__all__ = ["TemporaryAPIServer", "wait_for_api"]

_PR_SET_PDEATHSIG = 1


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class TemporaryAPIServer:
    """One temporary API server (``url``), its database in ``$PREFECT_HOME`` as Prefect's own."""

    def __init__(self, process: subprocess.Popen, port: int, log: Path | None):
        self.process, self.port, self._log = process, port, log

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}/api"

    @classmethod
    def launch(cls, log: Path | None = None, *, without: Sequence[str] = ()) -> TemporaryAPIServer:
        """Start the server process, without waiting for it. Call it from the thread that lives as
        long as the server should: the kernel's signal follows the thread that started the child.
        ``log``: a file for the server's own output (default: this process's stderr; it says
        only errors). ``without``: Prefect server services not to run (names as in
        ``PREFECT_SERVER_SERVICES_<NAME>_ENABLED``, e.g. ``task_run_recorder``), and
        ``"block_registration"``: no block types registered at start."""
        spec = importlib.util.find_spec("prefect")
        if spec is None or not spec.submodule_search_locations:
            raise RuntimeError("prefect is not installed: cannot start a Prefect API server")
        app_dir = Path(next(iter(spec.submodule_search_locations))).parent
        parent, port = os.getpid(), _free_port()

        def die_with_parent() -> None:  # in the child, before uvicorn starts
            ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
            if os.getppid() != parent:  # the parent died before the line above
                os._exit(0)

        # no UI; ephemeral: no scheduler or other services, what a temporary server needs
        env = {**os.environ, "PREFECT_UI_ENABLED": "0", "PREFECT__SERVER_EPHEMERAL": "1", "PREFECT__SERVER_FINAL": "1"}
        for name in without:
            key = ("PREFECT_API_BLOCKS_REGISTER_ON_START" if name == "block_registration"
                   else f"PREFECT_SERVER_SERVICES_{name.upper()}_ENABLED")
            env[key] = "false"
        out = open(log, "ab") if log is not None else None  # noqa: SIM115 - the child's from here
        try:
            process = subprocess.Popen(
                [sys.executable, "-m", "uvicorn", "--app-dir", str(app_dir), "--factory",
                 "prefect.server.api.server:create_app", "--host", "127.0.0.1", "--port", str(port),
                 "--log-level", "error", "--lifespan", "on"],
                env=env, stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT if out else None,
                preexec_fn=die_with_parent)
        finally:
            if out is not None:
                out.close()
        return cls(process, port, log)

    def wait_ready(self, timeout_s: float = 120) -> str:
        """Wait until the server answers its health check; returns ``url``. Raises RuntimeError
        (what its log says) when it exits or does not answer within ``timeout_s``."""
        return wait_for_api(self.url, timeout_s, exited=self._exited)

    def _exited(self) -> str | None:
        if self.process.poll() is None:
            return None
        return (f"the Prefect API server on port {self.port} exited with status {self.process.returncode}"
                f"{self._log_tail()}")

    def stop(self, timeout_s: float = 10) -> None:
        """Stop the server (SIGTERM, then SIGKILL after ``timeout_s``)."""
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()

    def _log_tail(self) -> str:
        if self._log is None or not self._log.is_file():
            return ""
        lines = self._log.read_text(errors="replace").strip().splitlines()
        return f"; its log ({self._log}) ends: {lines[-1]}" if lines else ""


def wait_for_api(url: str, timeout_s: float = 120, *, exited=lambda: None) -> str:
    """Wait until the Prefect API at ``url`` answers its health check; returns ``url``. Raises
    RuntimeError after ``timeout_s``, or as soon as ``exited()`` says why the server is gone."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with urllib.request.urlopen(f"{url}/health", timeout=5) as response:
                if response.status == 200:
                    return url
        except (urllib.error.URLError, ConnectionError, TimeoutError):
            pass
        if (why := exited()) is not None:
            raise RuntimeError(why)
        if time.monotonic() > deadline:
            raise RuntimeError(f"the Prefect API at {url} did not answer within {timeout_s:g} s")
        time.sleep(0.1)
