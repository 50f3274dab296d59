"""The ``reconstruct_batch`` flow: every sample in the catalog that is new, failed or changed is
reconstructed, each as a subflow run of ``reconstruct_sample``, at most ``max_concurrent`` at a
time (a Prefect global concurrency limit made for the batch run, visible in the UI, removed at its
end); one sample failing never stops the others. Returns (and logs) a summary.
"""

from __future__ import annotations

import contextlib
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from prefect import flow, get_run_logger, task
from prefect.cache_policies import NO_CACHE
from prefect.concurrency.sync import concurrency
from prefect.task_runners import ThreadPoolTaskRunner

from data_catalog import audit
from data_catalog.catalog import Catalog, SampleRecord
from flows import stopping
from flows.qa_index import write_index
from flows.reconstruct import reconstruct_sample

__all__ = ["reconstruct_batch", "reconstruct_one"]


def _failed_stage(out_dir: Path) -> str | None:
    """The stage the sample's last run failed in, from its audit trail."""
    try:
        entries = audit.read_trail(out_dir)
    except FileNotFoundError:
        return None
    for entry in reversed(entries):
        if entry.get("kind") == "run-failed":
            return entry.get("stage")
        if entry.get("kind") == "run-started":
            return None
    return None


@task(name="reconstruct-one", task_run_name="sample {record.sample_id}", cache_policy=NO_CACHE)
def reconstruct_one(workspace: str, record: SampleRecord, config_path: str | None, started_by: str,
                    limit: str | None = None) -> dict[str, Any]:
    """One sample as a subflow run; its outcome goes into the catalog and is returned, never raised.
    ``limit`` names the Prefect global concurrency limit that bounds how many run at once."""
    if limit is None:
        return _reconstruct_one(workspace, record, config_path, started_by)
    with concurrency(limit, occupy=1, strict=True):
        return _reconstruct_one(workspace, record, config_path, started_by)


def _reconstruct_one(workspace: str, record: SampleRecord, config_path: str | None, started_by: str) -> dict[str, Any]:
    from prefect.runtime import flow_run

    catalog = Catalog(Path(workspace))
    out_dir = catalog.out_dir_for(record.sample_id)
    catalog.mark_running(record.sample_id, out_dir, str(flow_run.id) if flow_run.id else None)
    try:
        run = reconstruct_sample(record.sample_dir, str(out_dir), config_path, started_by=started_by,
                                    sample_id=record.sample_id,
                                    trail_head=record.trail_head["hash"] if record.trail_head else None)
    except Exception as exc:  # noqa: BLE001 - a failed sample is recorded, the batch goes on
        # failed before any stage (the sample folder gone or changed since it was registered): the checks
        stage = getattr(exc, "stage", None) or _failed_stage(out_dir) or "preflight"
        message = f"{type(exc).__name__}: {exc}"
        catalog.mark_failed(record.sample_id, stage, message)
        return {"sample_id": record.sample_id, "state": "failed", "stage": stage, "error": message}
    artefacts = {name: item["sha256"] for name, item in run.outputs.items()}
    catalog.mark_done(record.sample_id, record.fingerprint, artefacts,  # as taken just before the run
                      trail_head={"seq": run.trail_head.seq, "hash": run.trail_head.hash})
    return {"sample_id": record.sample_id, "state": "done", "out_dir": str(out_dir),
            "cached_stages": sorted(k for k, v in run.cached.items() if v)}


@contextlib.contextmanager
def _batch_limit(slots: int) -> Iterator[str]:
    """A Prefect global concurrency limit of ``slots`` for one batch run; deleted afterwards."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.actions import GlobalConcurrencyLimitCreate
    from prefect.runtime import flow_run

    name = f"weldrecon-batch-{flow_run.id or uuid.uuid4()}"
    with get_client(sync_client=True) as client:
        client.create_global_concurrency_limit(GlobalConcurrencyLimitCreate(name=name, limit=slots))
    try:
        yield name
    finally:
        with get_client(sync_client=True) as client:
            client.delete_global_concurrency_limit_by_name(name)


@flow(name="reconstruct-batch", task_runner=ThreadPoolTaskRunner(max_workers=8), log_prints=False)
def reconstruct_batch(workspace: str, samples_root: str | None = None, config_path: str | None = None,
                      max_concurrent: int = 1, started_by: str | None = None) -> dict[str, Any]:
    """Register the sample folders under ``samples_root`` (when given) in ``workspace``'s catalog,
    then reconstruct every sample that is due. ``max_concurrent`` samples run at once."""
    stopping.reassert()  # Prefect's engine put its SIGTERM handler in place: the command's stops the batch
    log = get_run_logger()
    # every path absolute before any sample runs: MeshLab's Poisson changes the process's working
    # directory while it meshes one sample, and the others go on meanwhile
    workspace = str(Path(workspace).resolve())
    config_path = str(Path(config_path).resolve()) if config_path is not None else None
    catalog = Catalog(Path(workspace))
    refused: list[str] = []
    registered: list[SampleRecord] = []
    if samples_root is not None:
        registered, refused = catalog.scan(Path(samples_root))
        for line in refused:
            log.warning("not registered: %s", line)
    unreadable: dict[str, str] = {}
    due = catalog.due(fresh=[r.sample_id for r in registered], unreadable=unreadable)
    for sample_id, why in unreadable.items():
        log.warning("sample %s: %s", sample_id, why)
    log.info("%d sample(s) due: %s", len(due), ", ".join(r.sample_id for r in due) or "none")
    trigger = started_by or "batch"
    if max_concurrent < 1:
        raise ValueError(f"max_concurrent must be >= 1, got {max_concurrent}")
    with _batch_limit(max_concurrent) as limit:
        futures = [reconstruct_one.submit(workspace, record, config_path, trigger, limit) for record in due]
        results = [f.result() for f in futures]
    failed = {r["sample_id"]: {"stage": r["stage"], "error": r["error"]} for r in results if r["state"] == "failed"}
    failed.update({sample_id: {"stage": "register", "error": why} for sample_id, why in unreadable.items()})
    summary = {"done": [r["sample_id"] for r in results if r["state"] == "done"],
               "failed": dict(sorted(failed.items())),
               "not_registered": refused,
               "up_to_date": sorted({r.sample_id for r in catalog.list()}
                                    - {r.sample_id for r in due} - set(unreadable))}
    for sample_id, why in summary["failed"].items():
        log.error("sample %s failed at %s: %s", sample_id, why["stage"], why["error"])
    log.info("batch: %d done, %d failed, %d up to date", len(summary["done"]), len(summary["failed"]),
             len(summary["up_to_date"]))
    try:
        summary["index"] = str(write_index(Path(workspace)))
    except Exception as exc:  # noqa: BLE001 - the samples are done; the index is a view of them
        log.warning("could not write the batch index page: %s", exc)
        summary["index"] = None
    return summary
