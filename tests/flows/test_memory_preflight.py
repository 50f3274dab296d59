"""A run the machine cannot hold is refused before any work, with one line naming what it needs
and what there is (issue 28: a run under a memory limit died with a shared-library or libgomp
message). The limit is a real memory cgroup (v1 here, as on the machines this runs on)."""

from __future__ import annotations

import os
import subprocess
import sys
import uuid
from pathlib import Path

import pytest

from flows.preflight import load_config, memory_needed_bytes
from tests.flows.cli import cli_env
from tests.flows.samples import QUICK_CONFIG

REPO = Path(__file__).resolve().parents[2]
CGROUPS = Path("/sys/fs/cgroup/memory")
GB = 2 ** 30


def test_the_floor_stays_under_every_run_measured():
    """The peak RSS measured (flows/preflight.py): depth 8 0.84 GB (ci six-pass subset), 10 2.33 GB
    (demo), 12 4.6 GB (tjoint) and 8.0 GB (paper): the floor refuses none of them where it fits."""
    for config, measured_gb in ((QUICK_CONFIG, 0.84), (REPO / "deploy" / "configs" / "demo.yaml", 2.33),
                                (None, 4.6)):
        needed = memory_needed_bytes(load_config(config)) / GB
        assert 0.4 < needed < measured_gb


@pytest.mark.skipif(not os.access(CGROUPS, os.W_OK), reason="needs a writable cgroup v1 memory controller (root)")
def test_a_run_in_a_cgroup_too_small_is_refused_with_one_line(six_sample, tmp_path):
    group = CGROUPS / f"weldrecon-test-{uuid.uuid4().hex[:8]}"
    group.mkdir()
    try:
        (group / "memory.limit_in_bytes").write_text(str(400 * 2 ** 20))
        out = tmp_path / "run"
        command = (f'echo $$ > {group / "cgroup.procs"} && exec {sys.executable} -m flows.cli reconstruct '
                   f'{six_sample} --out {out} --config {QUICK_CONFIG}')
        done = subprocess.run(["sh", "-c", command], cwd=REPO, env=cli_env(), capture_output=True, text=True,
                              timeout=120)
    finally:
        group.rmdir()
    assert done.returncode == 2
    [line] = done.stderr.splitlines()
    assert line.startswith("weldrecon reconstruct: error: not enough memory for this run: it needs at least 0.5 GB "
                           "(mesh.poisson_depth 8; no run measured at that depth took less), 0.")
    assert f"GB is available (the memory cgroup /{group.name}'s limit 0.4 GB, 0." in line
    assert line.endswith("give it more memory or a lower mesh.poisson_depth")
    assert not out.exists()


@pytest.mark.parametrize("exc", [
    ImportError("libgomp.so.1: failed to map segment from shared object"),
    OSError(12, "Cannot allocate memory"),
    OSError("libgomp: Thread creation failed: Resource temporarily unavailable"),
], ids=["library", "allocation", "threads"])
def test_a_run_that_meets_the_limit_later_says_out_of_memory_in_one_line(exc, tmp_path, monkeypatch, capsys):
    """The floor lets a run start that then needs more than there is: what the loader or libgomp
    says then is named as out of memory, one line, the traceback in the log."""
    from flows.cli.errors import say_error

    monkeypatch.setenv("WELDRECON_LOG_DIR", str(tmp_path))
    assert say_error("reconstruct", exc) == 2
    first, second = capsys.readouterr().err.splitlines()
    assert first == (f"weldrecon reconstruct: error: out of memory ({exc}); give the run more memory (the least it "
                     "needs: flows/preflight.py, MEMORY_FLOOR_BYTES)")
    assert second.startswith("  (the details and the traceback: ")
