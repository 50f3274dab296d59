"""The reconstruction on a Dask cluster of local worker processes (prefect-dask's task runner):
the per-pass work runs in other processes, data moves through the zarr stage store only, the
workers reach one Prefect API started for the run, and the results equal the threaded run's,
byte for byte."""

from __future__ import annotations

import os
from pathlib import Path

from data_catalog.audit import read_trail, verify_trail
from flows.stages import STAGE_NAMES
from flows.stages.qa_audit import strip_audit
from tests.flows.samples import QUICK_CONFIG, as_published

REPO = Path(__file__).resolve().parents[2]
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")


def _servers_marked(marker: str) -> set[int]:
    """Prefect API servers (uvicorn) of this machine whose environment holds ``marker``."""
    found = set()
    for proc in Path("/proc").iterdir():
        try:
            if (proc.name.isdigit() and b"prefect.server.api.server:create_app" in (proc / "cmdline").read_bytes()
                    and marker.encode() in (proc / "environ").read_bytes()):
                found.add(int(proc.name))
        except OSError:
            continue
    return found


def test_a_sample_on_a_local_dask_cluster(six_run, six_sample, tmp_path, monkeypatch, collected_after):
    import threading
    import uuid

    from flows.reconstruct import prefect_api_for_workers, reconstruct_sample

    _, threaded = six_run
    out = tmp_path / "dask-run"
    marker = f"dask-test-{uuid.uuid4()}"
    monkeypatch.setenv("WELDRECON_TEST_MARKER", marker)  # inherited by the workers and anything they start
    seen: set[int] = set()
    running = threading.Event()

    def watch() -> None:  # a worker that started a server of its own would show here while it runs
        while not running.wait(0.5):
            seen.update(_servers_marked(marker))

    watcher = threading.Thread(target=watch)
    watcher.start()
    try:
        with prefect_api_for_workers():
            report = as_published(reconstruct_sample(str(six_sample), str(out), QUICK_CONFIG, started_by="pytest dask", dask="local:2"))
    finally:
        running.set()
        watcher.join()
    assert seen == set() and _servers_marked(marker) == set()  # the workers used the run's API server
    stages = [e for e in read_trail(out) if e["kind"] == "stage"]
    per_pass = {e["pid"] for e in stages if e.get("item") is not None}
    assert os.getpid() not in per_pass and len(per_pass) == 2  # two worker processes did the per-pass work
    # same inputs, settings and code: the same keys and the same bytes, to the STL
    assert report["stage_keys"] == threaded["stage_keys"]
    outputs = {(e["stage"], e.get("item")): e["record"]["outputs"] for e in stages}
    threaded_trail = read_trail(six_run[0])  # its first run (later tests rerun that folder with other settings)
    end = next(i for i, e in enumerate(threaded_trail) if e["kind"] == "run-finished")
    first = {(e["stage"], e.get("item")): e["record"]["outputs"] for e in threaded_trail[:end] if e["kind"] == "stage"}
    assert {s for s, _ in outputs} == set(STAGE_NAMES)
    assert all(first[k] == v for k, v in outputs.items())
    # every published file the same bytes; the QA report's but for its audit section (each run
    # folder's own trail), which it is, drawn by the stage, once that section is taken out
    assert {k: v["sha256"] for k, v in report["outputs"].items() if k != "report.html"} == \
        {k: v["sha256"] for k, v in threaded["outputs"].items() if k != "report.html"}
    assert strip_audit(Path(report["outputs"]["report.html"]["path"]).read_text()) == \
        strip_audit(Path(threaded["outputs"]["report.html"]["path"]).read_text())
    assert verify_trail(out) == []
