"""The temporary Prefect API server (flows.api_server): a server that cannot start is named with
what its log says, and one that never answers is given up after the time asked for. (That it
answers, serves the run's own flow and dies with its parent: tests/conftest.py starts one for
every test process; tests/flows/test_resilience_audit.py kills a run under one.)"""

from __future__ import annotations

import subprocess
import sys

import pytest

from flows.api_server import TemporaryAPIServer, wait_for_api


def test_a_server_that_exits_is_named_with_the_last_line_of_its_log(tmp_path):
    log = tmp_path / "server.log"
    with open(log, "wb") as out:
        process = subprocess.Popen([sys.executable, "-c", "import sys; print('address already in use'); sys.exit(3)"],
                                   stdout=out, stderr=subprocess.STDOUT)
    server = TemporaryAPIServer(process, 9, log)
    with pytest.raises(RuntimeError, match=r"the Prefect API server on port 9 exited with status 3; its log "
                                           r"\(.*server.log\) ends: address already in use"):
        server.wait_ready(timeout_s=30)


def test_an_api_that_never_answers_is_given_up_after_the_time_asked_for():
    with pytest.raises(RuntimeError, match=r"the Prefect API at http://127.0.0.1:9/api did not answer within 0.5 s"):
        wait_for_api("http://127.0.0.1:9/api", timeout_s=0.5)
