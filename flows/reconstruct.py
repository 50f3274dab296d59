"""The ``reconstruct_sample`` Prefect flow: the stages of ``flows.stages.STAGES`` wired in their
order. Per-pass stages are mapped over the passes and run in parallel (threads here, or worker
processes on a Dask cluster); each whole-sample stage starts when the stages it needs are done.

Tasks are thin: each runs one stage through ``flows.stages.run_stage`` and passes on a small
``StageRef`` (store path + content hashes), never point arrays. IO failures are retried with
back-off; bad input is not.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from prefect import flow, get_run_logger, task, unmapped
from prefect.cache_policies import NO_CACHE
from prefect.futures import as_completed
from prefect.task_runners import ThreadPoolTaskRunner

from data_catalog import audit
from data_catalog.atomic import folder_lock, sweep_leftovers
from data_catalog.manifests import MANIFEST_NAME, check_pass_file, check_sample_files, load_manifest
from data_catalog.passes import pass_is_complete
from data_catalog.stages import StageStore
from flows import stopping
from flows.preflight import (check_dask_scheduler, check_out_dir, check_run_folder, check_settings, load_config,
                             trail_problems, wait_for_file)
from flows.stages import (STAGE_NAMES, STAGES, Stage, StageFailed, StageRef, code_version, needed_for,
                          run_stage)
from flows.stages.contracts import each
from flows.stages.outputs import REPORT
from flows.stages.report import RESULTS, publish
from schemas.manifest import PassEntry, SampleManifest
from schemas.reconstruction import ReconstructionConfig
from schemas.stage_documents import Report

__all__ = ["RunResult", "TrailHead", "check_out_dir", "check_run_folder", "reconstruct_sample", "load_config", "ReconstructionFailed", "task_runner", "prefect_api_for_workers",
           "wait_for_file"]


class ReconstructionFailed(RuntimeError):
    """A stage failed; ``stage`` names it, the message names the passes and why."""

    def __init__(self, stage: str | None, message: str) -> None:
        super().__init__(message)
        self.stage = stage

    def __reduce__(self):
        return (ReconstructionFailed, (self.stage, str(self)))


def _io_failure(task, task_run, state) -> bool:  # noqa: ANN001 - Prefect's retry hook signature
    """Retry only what may pass on a second try: IO errors, not bad input."""
    try:
        state.result()
    except StageFailed as exc:
        return exc.retryable
    except OSError:
        return True
    except Exception:  # noqa: BLE001 - anything else is final
        return False
    return False


PUBLISH_LOCK = Path("audit") / "publish.lock"

_TASK = dict(cache_policy=NO_CACHE, retries=2, retry_delay_seconds=[1, 4], retry_condition_fn=_io_failure)


def _stage_task(stage: Stage):
    """The Prefect task of one stage, named as the stage (per pass: ``<stage> <pass>``)."""

    def run(store: StageStore, sample_dir: Path, manifest: SampleManifest, config: ReconstructionConfig,
            inputs: dict[str, Any], entry: PassEntry | None = None) -> StageRef:
        return run_stage(stage, store=store, sample_dir=sample_dir, manifest=manifest, config=config, inputs=inputs,
                         entry=entry)

    run_name = f"{stage.name} {{entry.pass_id}}" if stage.per_pass else stage.name
    run.__name__ = run.__qualname__ = f"stage_{stage.name}"
    return task(name=stage.name, task_run_name=run_name, description=stage.summary, **_TASK)(run)


STAGE_TASKS = {s.name: _stage_task(s) for s in STAGES}


def _gather(stage: str, pending) -> Any:
    """The refs of a submitted stage; for per-pass stages every failing pass is named."""
    if not isinstance(pending, list):
        return pending.result()
    results, failures = [], []
    for future in pending:
        try:
            results.append(future.result())
        except Exception as exc:  # noqa: BLE001 - collected and raised below
            failures.append(str(exc))
    if failures:
        raise ReconstructionFailed(stage, f"stage {stage} failed for {len(failures)} pass(es):\n  "
                                   + "\n  ".join(failures))
    return results


def _run_when_ready(stages: list[Stage], done: dict[str, Any], submit) -> dict[str, Any]:
    """Run the whole-sample ``stages``, each submitted (``submit(stage, inputs)``: a future) as soon
    as every stage it needs is in ``done`` or has finished here, so that independent stages run side
    by side (the stress beside the mesh: 131 s of the paper preset's final wait);
    their refs by name. A failure submits nothing more, lets the running stages end, and raises
    the failure of the first failed stage in registry order. Each stage's outputs are a function of
    its inputs alone: the order they finish in changes no byte."""
    refs: dict[str, Any] = {}
    waiting, running, failed = list(stages), {}, {}
    while waiting or running:
        if not failed:
            for stage in [s for s in waiting if all(n in done or n in refs for n in s.needs)]:
                waiting.remove(stage)
                running[stage.name] = submit(stage, {n: refs[n] if n in refs else done[n] for n in stage.needs})
        if not running:
            break
        finished = next(as_completed(list(running.values())))
        name = next(n for n, f in running.items() if f is finished)
        del running[name]
        try:
            refs[name] = finished.result()
        except Exception as exc:  # noqa: BLE001 - raised below, in registry order, once the running stages end
            failed[name] = exc
    if failed:
        raise failed[next(s.name for s in stages if s.name in failed)]
    return refs


def _trigger(started_by: str | None) -> dict[str, Any]:
    """Who or what started this run: the caller's word, the deployment and its schedule, the
    parent flow run (a batch), and the Prefect run ids."""
    import getpass
    import socket

    from prefect.runtime import deployment, flow_run

    info: dict[str, Any] = {"flow_run_id": str(flow_run.id) if flow_run.id else None,
                            "flow_run_name": flow_run.name, "parent_flow_run_id": flow_run.parent_flow_run_id,
                            "deployment_id": deployment.id, "deployment_name": deployment.name,
                            "host": socket.gethostname(), "user": getpass.getuser()}
    auto_scheduled = False
    if deployment.id and flow_run.id:
        try:
            from prefect.client.orchestration import get_client

            with get_client(sync_client=True) as client:
                auto_scheduled = bool(client.read_flow_run(flow_run.id).auto_scheduled)
        except Exception:  # noqa: BLE001 - the trigger is recorded as well as it can be
            pass
    if started_by:
        info["started_by"] = started_by
    elif deployment.id:
        info["started_by"] = "schedule" if auto_scheduled else "deployment"
    elif flow_run.parent_flow_run_id:
        info["started_by"] = "batch"
    else:
        info["started_by"] = "python"
    return info


def task_runner(dask: str | None):
    """The per-pass work's task runner: threads in this process without ``dask``; with it, a Dask
    cluster through prefect-dask: ``local:N`` starts N worker processes here, anything else is a
    scheduler address (``tcp://host:8786``). Workers exchange only stage references; the data
    goes through the zarr stage store, which must then be on a path every worker sees, and the
    workers must reach the Prefect API (``prefect_api_for_workers``)."""
    if not dask:
        return ThreadPoolTaskRunner(max_workers=2)
    from prefect_dask import DaskTaskRunner

    if dask.startswith("local:"):
        try:
            workers = int(dask.split(":", 1)[1])
        except ValueError:
            workers = 0
        if workers < 1:
            raise ValueError(f"dask {dask!r}: local:N needs a number N >= 1 of worker processes")
        return DaskTaskRunner(cluster_class="distributed.LocalCluster",
                              cluster_kwargs={"n_workers": workers, "threads_per_worker": 1, "processes": True,
                                              "dashboard_address": None})
    check_dask_scheduler(dask)
    return DaskTaskRunner(address=dask)


@contextlib.contextmanager
def prefect_api_for_workers(startup_timeout_s: int = 120) -> Iterator[str]:
    """A Prefect API that worker processes reach: ``PREFECT_API_URL`` when it is set; otherwise one
    temporary local server for this run (flows.api_server: stopped by the kernel if this process
    dies), exported to the environment that worker processes inherit (without it every worker
    would start a server of its own, which on a busy machine times out). Yields the API URL.
    Enter it from the main thread: the server lives as long as the thread that started it."""
    from prefect.settings import PREFECT_API_URL, temporary_settings

    from flows.api_server import TemporaryAPIServer

    configured = os.environ.get("PREFECT_API_URL") or PREFECT_API_URL.value()
    if configured:
        yield configured
        return
    server = TemporaryAPIServer.launch()
    try:
        try:
            url = server.wait_ready(startup_timeout_s)
        except RuntimeError as exc:
            raise RuntimeError(f"could not start a local Prefect API server for the workers: {exc}") from None
        os.environ["PREFECT_API_URL"] = url  # for the worker processes; this one's settings are read at import
        try:
            with temporary_settings(updates={PREFECT_API_URL: url}):  # this process's own client too
                try:
                    yield url
                finally:
                    from prefect.logging.handlers import APILogHandler

                    with contextlib.suppress(Exception):  # best effort: the last log lines while the server listens
                        APILogHandler().flush()
        finally:
            os.environ.pop("PREFECT_API_URL", None)
    finally:
        server.stop()


def audit_status(out: Path) -> dict[str, Any]:
    """The run folder's trail as the QA report states it when published: the chain verified (not
    the artefacts' contents: the run has just recorded its own), this run's own missing end aside."""
    problems = [p for p in audit.verify_trail(out, artefacts=False) if p.kind != "unfinished-run"]
    entries = audit.read_trail(out)
    last = entries[-1] if entries else {}
    return {"intact": not problems, "entries": len(entries), "head_seq": last.get("seq"), "head_hash": last.get("hash"),
            "problems": [str(p) for p in problems]}


@dataclass(frozen=True)
class TrailHead:
    """The run-finished entry of the audit trail: an anchor to keep outside the run folder."""

    seq: int
    hash: str


@dataclass(frozen=True)
class RunResult:
    """What a reconstruction run hands back: the published report (``results/report.json``), the
    published files (name -> path and sha256), every stage's refs, which stages were all cached,
    the seconds each stage's bodies took, and the trail's head."""

    report: Report | None  # None: a run stopped after a named stage (nothing published)
    outputs: dict[str, dict[str, str]]
    refs: dict[str, Any]
    cached: dict[str, bool]
    seconds: dict[str, float]
    trail_head: TrailHead

    def stage_path(self, name: str) -> str | list[str]:
        """A stage's folder in the stage store (a list for per-pass stages)."""
        ref = self.refs[name]
        return [r.path for r in ref] if isinstance(ref, list) else ref.path


def _link_the_reports(sample_id: str, report: Report, published: dict[str, dict[str, str]], log) -> None:
    """Prefect artifacts on this flow run: a link to the sample's QA report and a summary table,
    so the Prefect UI leads from each run to its report. Best effort: a run is not failed for it."""
    import re

    from prefect.artifacts import create_link_artifact, create_markdown_artifact

    if "report.html" not in published:
        return
    key = re.sub(r"[^a-z0-9-]+", "-", f"qa-report-{sample_id}".lower()).strip("-")[:100]
    path = Path(published["report.html"]["path"])
    weld, checks, volume = report.weld, report.checks, report.volume_mesh
    flagged = [c for c in checks if c.result != "ok"]
    rows = [("checks", f"{len(checks) - len(flagged)} of {len(checks)} ok"),
            ("weld", f"{weld.verdict}, {weld.sections} sections, {weld.failing or 0} failing"
             if weld.measured else f"not measured: {weld.why_not}"),
            ("FE model", f"{volume.solid.tetrahedra} tetrahedra" if volume.made else f"not made: {volume.why}"),
            ("QA report", f"[{path.name}]({path.as_uri()})"), ("report.html sha256", published["report.html"]["sha256"])]
    table = "\n".join(f"| {k} | {v} |" for k, v in rows)
    try:
        create_link_artifact(key=key, link=path.as_uri(), link_text=f"QA report {sample_id}",
                             description=f"The QA report of sample {sample_id} (self-contained HTML).")
        create_markdown_artifact(key=f"{key}-summary"[:100], markdown=f"## Sample {sample_id}\n\n| | |\n|---|---|\n{table}\n",
                                 description=f"QA summary of sample {sample_id}")
    except Exception as exc:  # noqa: BLE001 - the results are published; the link is a convenience
        log.warning("could not create the Prefect artifacts linking the QA report: %s", exc)


def _on_dask() -> bool:
    from prefect.context import FlowRunContext

    context = FlowRunContext.get()
    return context is not None and type(context.task_runner).__name__ == "DaskTaskRunner"


def _submit_as_passes_land(sample: Path, manifest: SampleManifest, store: StageStore, config: ReconstructionConfig,
                           timeout_s: float, log, provisional=None) -> dict[str, list]:
    """Follow a scan in progress: each pass's per-pass stages are submitted as soon as its store is
    complete on disk, in the manifest's order (the robot's); ``provisional`` (a
    ``flows.provisional.ProvisionalWeld``) is told of each pass and its stages."""
    pending: dict[str, list] = {}
    for setup, entry in manifest.passes():
        wait_for_file(sample / entry.file, timeout_s=timeout_s, what=f"pass {entry.pass_id} (setup {setup})",
                      ready=pass_is_complete)
        check_pass_file(sample, manifest, setup, entry)
        log.info("pass %s landed", entry.pass_id)
        for stage in STAGES:
            if stage.per_pass:
                pending.setdefault(stage.name, []).append(
                    STAGE_TASKS[stage.name].submit(store, sample, manifest, config, {}, entry))
        if provisional is not None:
            provisional.landed(entry, pending["denoise"][-1], pending["targets"][-1])
    return pending


@flow(name="reconstruct-sample", task_runner=ThreadPoolTaskRunner(max_workers=2), log_prints=False)
def reconstruct_sample(sample_dir: str, out_dir: str, config_path: str | None = None, started_by: str | None = None,
                       dask: str | None = None, follow_timeout_s: float | None = None,
                       sample_id: str | None = None, trail_head: str | None = None,
                       stop_after: str | None = None) -> RunResult:
    """Reconstruct one sample folder (manifest + passes) into ``out_dir``.

    The manifest and the pass files' sizes and paths are checked before any work; every stage
    and the run itself go into ``out_dir``'s audit trail (data_catalog.audit). ``dask`` (or, when
    not given, ``$WELDRECON_DASK`` read at run time): run the stages on a Dask cluster (see
    ``task_runner``). ``follow_timeout_s``: follow a scan in progress: the manifest (the scan
    plan) may still be coming, and each pass's stages start as soon as its store is complete on
    disk, waiting at most this long for each (the whole-sample stages follow the last pass).
    ``sample_id``: the sample the caller means (the catalog's); a folder whose manifest names
    another is refused, and so is a run folder that holds another sample's runs. ``trail_head``:
    the hash of the run-finished entry the caller kept (the catalog's); a trail that no longer holds
    it, or is otherwise not intact, is recorded as such (``trail-problems-found``) before this run
    appends to it, and ``audit verify`` names that entry from then on. ``stop_after``: run this
    stage and the stages it needs (``flows.stages.needed_for``) and stop: nothing is published,
    the trail records "run-stopped", the result has no report.

    The deliverables, the report and the settings they were made with are published into
    ``out_dir/results/`` as one unit, and the run-finished entry that records them is appended
    under the same lock: a concurrent run of the folder publishes before or after, never
    between. The returned report carries ``trail_head`` (that entry's seq and hash), an anchor
    to keep outside the folder (the catalog keeps it) against which a shortened trail fails."""
    dask = dask or os.environ.get("WELDRECON_DASK") or None
    if dask and not _on_dask():
        return reconstruct_sample.with_options(task_runner=task_runner(dask))(
            sample_dir, out_dir, config_path, started_by, dask, follow_timeout_s, sample_id, trail_head, stop_after)
    if stop_after is not None and stop_after not in STAGE_NAMES:
        raise ValueError(f"stop after {stop_after!r}: no such stage; the stages are {', '.join(STAGE_NAMES)}")
    stopping.reassert()  # Prefect's engine put its SIGTERM handler in place: the command's stops the run
    log = get_run_logger()
    for stage in STAGES:  # import and hash the code now: an edit during a long run is not credited to it
        stage.load()
        code_version(stage)
    # absolute from here on: MeshLab's Poisson changes the process's working directory while it runs
    sample, out = Path(sample_dir).resolve(), Path(out_dir).resolve()
    if follow_timeout_s is not None:
        wait_for_file(sample / MANIFEST_NAME, timeout_s=follow_timeout_s, what=f"sample {sample}")
    check_out_dir(sample, out)
    manifest = load_manifest(sample)
    if sample_id is not None and manifest.sample_id != sample_id:
        raise ValueError(f"sample folder {sample}: its manifest names sample {manifest.sample_id}, not {sample_id} "
                         "(renamed, or the folder reused for another sample)")
    check_sample_files(sample, manifest)
    config = load_config(config_path)
    check_settings(manifest, config)
    check_run_folder(out, manifest.sample_id)
    found = trail_problems(out, trail_head)
    store = StageStore(out, trust_folder=not found)  # a trail that does not verify vouches for no stage
    out.mkdir(parents=True, exist_ok=True)
    audit.append(out, "run-started", sample_id=manifest.sample_id, sample_dir=str(sample),
                 config=config.model_dump(mode="json"), **_trigger(started_by))
    if found:  # recorded before this run's entries can make a cut or edited trail look whole again
        audit.append(out, audit.PROBLEMS_FOUND, problems=found)
    swept = sweep_leftovers(out)  # what runs of this folder that died (kill -9, power cut) left half written
    if swept:
        audit.append(out, "leftovers-swept", paths=[p.relative_to(out).as_posix() for p in swept])
    entries = [e for _, e in manifest.passes()]
    log.info("sample %s: %d passes in %d setups", manifest.sample_id, len(entries), len(manifest.setups))
    pending: dict[str, Any] = {}
    refs: dict[str, Any] = {}

    def outputs_of(name: str) -> Any:
        if name not in refs:
            refs[name] = _gather(name, pending.pop(name))
        return refs[name]

    provisional = None
    if follow_timeout_s is not None and stop_after is None:  # the weld verdict while the scan comes in
        from flows.provisional import ProvisionalWeld

        provisional = ProvisionalWeld(sample=sample, out=out, manifest=manifest, config=config, log=log)
    try:
        if follow_timeout_s is not None:
            pending.update(_submit_as_passes_land(sample, manifest, store, config, follow_timeout_s, log, provisional))
        if provisional is not None:
            # what the lab needs first, with the machine to itself: the verdict on every pass, the
            # provisional mesh, FE model, stress and QA page (on the paper preset 36-81, 67-119 and
            # 214-288 s after the last pass), then the whole-sample stages
            provisional.close()
        chosen = [s for s in (needed_for(stop_after) if stop_after else STAGES) if s.name not in pending]
        for stage in chosen:
            if stage.per_pass:  # not yet submitted as its passes landed
                pending[stage.name] = STAGE_TASKS[stage.name].map(
                    unmapped(store), unmapped(sample), unmapped(manifest), unmapped(config), unmapped({}), entries)
        for name in list(pending):  # the per-pass stages all finish first, failures named in registry order
            outputs_of(name)
        refs.update(_run_when_ready([s for s in chosen if not s.per_pass], refs,
                                    lambda stage, inputs: STAGE_TASKS[stage.name].submit(store, sample, manifest,
                                                                                         config, inputs)))
        cached = {n: all(r.cached for r in each(v)) for n, v in refs.items()}
        seconds = {n: sum(r.metrics.get("seconds", 0.0) for r in each(v)) for n, v in refs.items()}
        if stop_after is not None:
            stopped = audit.append(out, "run-stopped", sample_id=manifest.sample_id, after=stop_after, cached=cached)
            return RunResult(report=None, outputs={}, refs=refs, cached=cached, seconds=seconds,
                             trail_head=TrailHead(seq=stopped["seq"], hash=stopped["hash"]))
        if provisional is not None:
            provisional.close()
            if provisional.published or provisional.meshes or provisional.models:  # what was provisional and is no more
                audit.append(out, "provisional-superseded", sample_id=manifest.sample_id,
                             provisional=[p["seq"] for p in provisional.published],
                             provisional_meshes=[p["seq"] for p in provisional.meshes],
                             provisional_models=[p["seq"] for p in provisional.models])
        with folder_lock(out / PUBLISH_LOCK):  # results and the entry recording them, as one step
            published = publish(out, manifest.sample_id, refs["report"], refs,
                                config.model_dump_json(indent=2) + "\n", audit_status(out))
            finished = audit.append(out, "run-finished", sample_id=manifest.sample_id,
                                    artefacts={f"{RESULTS}/{name}": item["sha256"] for name, item in published.items()},
                                    cached=cached)
    except BaseException as exc:
        if provisional is not None:
            provisional.close(wait=False)
        audit.append(out, "run-failed", sample_id=manifest.sample_id, stage=getattr(exc, "stage", None),
                     error=f"{type(exc).__name__}: {exc}")
        raise
    report = REPORT.read_path(Path(published[REPORT.name]["path"]))
    _link_the_reports(manifest.sample_id, report, published, log)
    return RunResult(report=report, outputs=published, refs=refs, cached=cached, seconds=seconds,
                     trail_head=TrailHead(seq=finished["seq"], hash=finished["hash"]))
