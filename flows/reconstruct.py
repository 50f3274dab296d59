"""The ``reconstruct_sample`` Prefect flow: per-pass denoising and target detection in parallel,
then the registration graph, merging, segmentation, meshing, export and the report.

Tasks are thin: they call ``flows.stages`` and pass small references (store path + content
hash), never point arrays. IO failures are retried with back-off; bad input is not.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import yaml
from prefect import flow, get_run_logger, task, unmapped
from prefect.cache_policies import NO_CACHE
from prefect.task_runners import ThreadPoolTaskRunner
from pydantic import ValidationError

from data_catalog.atomic import atomic_write_text
from data_catalog import audit
from data_catalog.hashing import sha256_file
from data_catalog.manifests import check_sample_files, load_manifest
from data_catalog.stages import StageStore
from flows import stages
from schemas.manifest import SampleManifest
from schemas.reconstruction import ReconstructionConfig

__all__ = ["reconstruct_sample", "load_config", "ReconstructionFailed"]


class ReconstructionFailed(RuntimeError):
    """A stage failed; the message names the passes or the stage and why."""


def load_config(path: str | Path | None) -> ReconstructionConfig:
    """The reconstruction config: defaults, overridden by a YAML file's fields."""
    if path is None:
        return ReconstructionConfig()
    try:
        raw = yaml.safe_load(Path(path).read_text()) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise ValueError(f"{path}: cannot read the reconstruction config ({exc})") from None
    try:
        return ReconstructionConfig.model_validate(raw)
    except ValidationError as exc:
        lines = "\n".join(f"  {'.'.join(str(p) for p in e['loc']) or '(top level)'}: {e['msg']}" for e in exc.errors())
        raise ValueError(f"{path}: invalid reconstruction config:\n{lines}") from None


def _io_failure(task, task_run, state) -> bool:  # noqa: ANN001 - Prefect's retry hook signature
    """Retry only what may pass on a second try: IO errors, not bad input."""
    try:
        state.result()
    except OSError:
        return True
    except Exception:  # noqa: BLE001 - anything else is final
        return False
    return False


_TASK = dict(cache_policy=NO_CACHE, retries=2, retry_delay_seconds=[1, 4], retry_condition_fn=_io_failure)


@task(name="denoise-pass", task_run_name="denoise {entry.pass_id}", **_TASK)
def denoise_pass(store: StageStore, sample_dir: Path, manifest: SampleManifest, entry, config) -> stages.Ref:
    return stages.cloud_stage(store, sample_dir, manifest, entry, config)


@task(name="detect-targets", task_run_name="targets {entry.pass_id}", **_TASK)
def detect_pass_targets(store: StageStore, sample_dir: Path, manifest: SampleManifest, entry, config) -> stages.Ref:
    return stages.targets_stage(store, sample_dir, manifest, entry, config)


@task(name="registration-graph", **_TASK)
def register(store, manifest, target_refs, config) -> stages.Ref:
    return stages.register_stage(store, manifest, target_refs, config)


@task(name="refine-poses", **_TASK)
def refine(store, manifest, cloud_refs, register_ref, config) -> stages.Ref:
    return stages.refine_stage(store, manifest, cloud_refs, register_ref, config)


@task(name="merge", **_TASK)
def merge(store, manifest, cloud_refs, refine_ref, config) -> stages.Ref:
    return stages.merge_stage(store, manifest, cloud_refs, refine_ref, config)


@task(name="remove-unwanted-objects", **_TASK)
def segment(store, manifest, merge_ref, refine_ref, config) -> stages.Ref:
    return stages.segment_stage(store, manifest, merge_ref, refine_ref, config)


@task(name="mesh", **_TASK)
def mesh(store, manifest, segment_ref, config) -> stages.Ref:
    return stages.surface_stage(store, manifest, segment_ref, config)


@task(name="export", **_TASK)
def export(store, manifest, surface_ref) -> stages.Ref:
    return stages.export_stage(store, manifest, surface_ref)


def _publish(out_dir: Path, manifest: SampleManifest, refs: dict[str, Any], config: ReconstructionConfig) -> dict:
    """Copy the deliverables into ``results/`` and write the sample's report."""
    import shutil

    results = out_dir / "results"
    results.mkdir(exist_ok=True)
    outputs = {}
    for name in refs["export"]["outputs"]:
        tmp = results / f".{name}.partial"
        shutil.copyfile(Path(refs["export"]["path"]) / name, tmp)
        tmp.replace(results / name)
        outputs[name] = {"path": str(results / name), "sha256": sha256_file(results / name)}
    registration = json.loads((Path(refs["register"]["path"]) / "registration.json").read_text())
    registration["refinement"] = json.loads((Path(refs["refine"]["path"]) / "refine.json").read_text())

    def metrics(ref):
        return [dict(r["metrics"], cached=r["cached"]) for r in ref] if isinstance(ref, list) else \
            dict(ref["metrics"], cached=ref["cached"])

    report = {
        "sample_id": manifest.sample_id,
        "passes": [e.pass_id for _, e in manifest.passes()],
        "config": config.model_dump(),
        "stages": {name: metrics(ref) for name, ref in refs.items()},
        "registration": registration,
        "mesh": refs["mesh"]["metrics"],
        "outputs": outputs,
        "stage_keys": {k: ([r["key"] for r in v] if isinstance(v, list) else v["key"]) for k, v in refs.items()},
        "stage_paths": {k: ([r["path"] for r in v] if isinstance(v, list) else v["path"]) for k, v in refs.items()},
        "cached": {k: (all(r["cached"] for r in v) if isinstance(v, list) else v["cached"]) for k, v in refs.items()},
    }
    atomic_write_text(results / "report.json", json.dumps(report, indent=1, default=str) + "\n")
    return report


def _gather(futures, what: str) -> list[stages.Ref]:
    """Results of mapped per-pass tasks; every failure is named, not just the first."""
    results, failures = [], []
    for future in futures:
        try:
            results.append(future.result())
        except Exception as exc:  # noqa: BLE001 - collected and re-raised below
            failures.append(str(exc))
    if failures:
        raise ReconstructionFailed(f"{what} failed for {len(failures)} pass(es):\n  " + "\n  ".join(failures))
    return results


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


def task_runner(dask: str | None = None):
    """The per-pass work's task runner: threads in this process by default; with ``dask`` (or the
    environment's WELDRECON_DASK), a Dask cluster through prefect-dask: ``local:N`` starts N
    worker processes here, anything else is a scheduler address (``tcp://host:8786``). Workers
    exchange only store references; the data goes through the zarr stage store, which must then
    be on a path every worker sees."""
    import os

    dask = dask or os.environ.get("WELDRECON_DASK") or None
    if not dask:
        return ThreadPoolTaskRunner(max_workers=2)
    from prefect_dask import DaskTaskRunner

    if dask.startswith("local:"):
        workers = int(dask.split(":", 1)[1])
        if workers < 1:
            raise ValueError(f"WELDRECON_DASK={dask!r}: local:N needs N >= 1 worker processes")
        return DaskTaskRunner(cluster_class="distributed.LocalCluster",
                              cluster_kwargs={"n_workers": workers, "threads_per_worker": 1, "processes": True,
                                              "dashboard_address": None})
    return DaskTaskRunner(address=dask)


@flow(name="reconstruct-sample", task_runner=task_runner(), log_prints=False)
def reconstruct_sample(sample_dir: str, out_dir: str, config_path: str | None = None,
                       started_by: str | None = None) -> dict[str, Any]:
    """Reconstruct one sample folder (manifest + passes) into ``out_dir``.

    The manifest and the pass files' sizes and paths are checked before any work; every stage
    and the run itself go into ``out_dir``'s audit trail (data_catalog.audit)."""
    log = get_run_logger()
    sample = Path(sample_dir)
    manifest = load_manifest(sample)
    check_sample_files(sample, manifest)
    config = load_config(config_path)
    store = StageStore(Path(out_dir))
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    atomic_write_text(Path(out_dir) / "config.json", config.model_dump_json(indent=2) + "\n")
    audit.append(Path(out_dir), "run-started", sample_id=manifest.sample_id, sample_dir=str(sample.resolve()),
                 config=config.model_dump(mode="json"), **_trigger(started_by))
    stage = "cloud"
    try:
        entries = [e for _, e in manifest.passes()]
        log.info("sample %s: %d passes in %d setups", manifest.sample_id, len(entries), len(manifest.setups))
        clouds = denoise_pass.map(unmapped(store), unmapped(sample), unmapped(manifest), entries, unmapped(config))
        targets = detect_pass_targets.map(unmapped(store), unmapped(sample), unmapped(manifest), entries,
                                          unmapped(config))
        cloud_refs = _gather(clouds, "denoising")
        stage = "targets"
        target_refs = _gather(targets, "target detection")
        stage = "register"
        register_ref = register.submit(store, manifest, target_refs, config).result()
        log.info("registration: %s", register_ref["metrics"])
        stage = "refine"
        refine_ref = refine.submit(store, manifest, cloud_refs, register_ref, config).result()
        log.info("refinement: %s", refine_ref["metrics"])
        stage = "merge"
        merge_ref = merge.submit(store, manifest, cloud_refs, refine_ref, config).result()
        stage = "segment"
        segment_ref = segment.submit(store, manifest, merge_ref, refine_ref, config).result()
        log.info("specimen: %s", segment_ref["metrics"])
        stage = "mesh"
        mesh_ref = mesh.submit(store, manifest, segment_ref, config).result()
        log.info("mesh: %s", mesh_ref["metrics"])
        stage = "export"
        export_ref = export.submit(store, manifest, mesh_ref).result()
        refs = {"cloud": cloud_refs, "targets": target_refs, "register": register_ref, "refine": refine_ref,
                "merge": merge_ref, "segment": segment_ref, "mesh": mesh_ref, "export": export_ref}
        stage = "report"
        report = _publish(Path(out_dir), manifest, refs, config)
    except BaseException as exc:
        audit.append(Path(out_dir), "run-failed", sample_id=manifest.sample_id, stage=stage,
                     error=f"{type(exc).__name__}: {exc}")
        raise
    results = {f"results/{name}": item["sha256"] for name, item in report["outputs"].items()}
    results["results/report.json"] = sha256_file(Path(out_dir) / "results" / "report.json")
    audit.append(Path(out_dir), "run-finished", sample_id=manifest.sample_id, artefacts=results,
                 cached={k: v for k, v in report["cached"].items()})
    return report
