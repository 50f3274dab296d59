"""``weldrecon reconstruct``: one sample's registered point cloud, mesh, FE model and QA report.
Everything a run needs is checked before Prefect and the compute stack are imported."""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys
from pathlib import Path

from flows.cli.errors import log_to_file, quiet_prefect
from flows.cli.render import print_run_summary, print_stopped_run

__all__ = ["add_reconstruct", "run_reconstruct"]


def catalogued_head(args: argparse.Namespace, out: Path, sample_id: str) -> str | None:
    """The head the workspace's catalog keeps for the run folder ``out`` of ``sample_id``, where
    there is one, so that a run of a catalogued folder holds its trail to it, as a batch does: a
    trail re-chained by someone who knows the hashing is then not intact, and none of the folder's
    stages is trusted."""
    from flows.cli.catalog import existing_catalog, workspace

    catalog = existing_catalog(workspace(args))
    records = [r for r in catalog.runs_in(out) if r.sample_id == sample_id] if catalog else []
    return records[0].trail_head["hash"] if records and records[0].trail_head else None


def add_reconstruct(sub) -> None:
    rec = sub.add_parser("reconstruct", help="registered point cloud and watertight STL of one sample")
    rec.add_argument("sample_dir", metavar="SAMPLE_DIR", help="folder with manifest.json and the passes")
    rec.add_argument("--config", metavar="FILE", help="YAML file of reconstruction settings (schemas/reconstruction.py)")
    rec.add_argument("--out", metavar="DIR", help="output folder (default: SAMPLE_DIR-reconstruction beside it)")
    rec.add_argument("--dask", metavar="ADDRESS", help="run the per-pass work on a Dask cluster: a scheduler "
                                                       "address, or local:N for N local worker processes "
                                                       "(default: $WELDRECON_DASK, else threads here)")
    rec.add_argument("--stop-after", metavar="STAGE", help="run STAGE and the stages it needs (see "
                     "`weldrecon stages`) and stop; nothing is published")
    rec.add_argument("--follow", action="store_true", help="follow a scan in progress: start each pass's stages as "
                     "soon as its store is complete on disk (the manifest may come first)")
    rec.add_argument("--follow-timeout", type=float, default=1800.0, metavar="S",
                     help="with --follow: longest wait for the manifest and for each next pass (default 1800 s)")
    rec.set_defaults(func=run_reconstruct)


def run_reconstruct(args: argparse.Namespace) -> int:
    """The command (``demo`` runs it too, with only ``sample_dir``, ``out`` and ``config``)."""
    quiet_prefect()
    import getpass

    from data_catalog.manifests import check_sample_files, load_manifest
    from flows.preflight import (check_dask_scheduler, check_out_dir, check_run_folder, check_settings, load_config,
                                 wait_for_file)

    # everything a run needs is checked first, before Prefect and the compute stack are imported
    sample = Path(args.sample_dir)
    out = Path(args.out) if args.out else sample.parent / f"{sample.name}-reconstruction"
    check_out_dir(sample, out)
    follow = args.follow_timeout if getattr(args, "follow", False) else None
    if follow is not None and not follow > 0:
        raise ValueError(f"--follow-timeout {follow:g}: expected a number of seconds > 0")
    if follow is not None:  # a scan in progress: its manifest (the plan) may still be coming
        print(f"following {sample}: each pass is reconstructed as it lands", file=sys.stderr, flush=True)
        wait_for_file(sample / "manifest.json", timeout_s=follow, what=f"sample {sample}")
    manifest = load_manifest(sample)
    check_sample_files(sample, manifest)  # bad input is refused here, before a flow run
    check_settings(manifest, load_config(args.config))
    check_run_folder(out, manifest.sample_id)
    stop_after = getattr(args, "stop_after", None)
    if stop_after is not None:
        from flows.stages import STAGE_NAMES

        if stop_after not in STAGE_NAMES:
            raise ValueError(f"--stop-after {stop_after}: no such stage; the stages are {', '.join(STAGE_NAMES)}")
    from flows.stages import needed_for

    if stop_after is None or any(stage.name == "stress" for stage in needed_for(stop_after)):
        import shutil

        if shutil.which("ccx") is None:  # the run goes on: the stress stage says so, the rest is published
            print("CalculiX (ccx) is not installed: the stress stage will make no model (Debian package "
                  "calculix-ccx; `make setup` installs it)", file=sys.stderr, flush=True)
    dask = getattr(args, "dask", None) or os.environ.get("WELDRECON_DASK") or None
    if dask and not dask.startswith("local:"):
        check_dask_scheduler(dask)
    from flows.progress import TrailProgress
    from flows.reconstruct import prefect_api_for_workers, reconstruct_sample
    from flows.stages import STAGES, needed_for

    log_to_file(out / "logs", "reconstruct")
    n_passes = len(manifest.passes())
    upto = needed_for(stop_after) if stop_after else STAGES
    expected = [(s.name, n_passes if s.per_pass else 1) for s in upto]
    with contextlib.ExitStack() as stack:
        # the run's own temporary API server, which the kernel stops if this process dies
        # (Prefect's own would outlive a kill -9); Dask workers report to it too
        api = stack.enter_context(prefect_api_for_workers())
        if dask:
            print(f"Dask workers report to the Prefect API at {api}", file=sys.stderr, flush=True)
        stack.enter_context(TrailProgress(out, expected, stream=sys.stderr,
                                          plan=_plan_of(manifest, sample) if follow is not None else None))
        run = reconstruct_sample(str(sample), str(out), args.config, started_by=f"cli ({getpass.getuser()})",
                                 dask=dask, follow_timeout_s=follow, stop_after=stop_after,
                                 trail_head=catalogued_head(args, out, manifest.sample_id))
    if run.report is None:
        print_stopped_run(run, out, stop_after)
        return 0
    print_run_summary(run, out)
    return 0


def _plan_of(manifest, sample: Path):
    """The plan's predicted weld coverage (``tasks.pass_coverage``), said on the terminal before
    the passes come in; None, said in a line, where it cannot be predicted (advice only: the run
    goes on; the traceback goes to the log)."""
    from flows.progress import plan_text
    from tasks.pass_coverage import plan_coverage

    try:
        plan = plan_coverage(manifest, sample)
    except Exception as exc:  # noqa: BLE001 - a prediction that fails must not stop the reconstruction
        logging.getLogger("weldrecon").exception("the plan's weld coverage could not be predicted")
        print(f"the plan's weld coverage could not be predicted ({type(exc).__name__}: {exc}); the run goes on",
              file=sys.stderr, flush=True)
        return None
    for line in plan_text(plan):
        print(line, file=sys.stderr, flush=True)
    return plan
