"""The ``weldrecon`` command line."""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import sys
import time
from pathlib import Path

from pydantic import ValidationError

__all__ = ["main"]


def _describe(error: ValidationError) -> str:
    return "\n".join(f"  {'.'.join(str(p) for p in e['loc']) or '(top level)'}: {e['msg']}" for e in error.errors())


def _deep_merge(base: dict, override: dict) -> dict:
    out = dict(base)
    for key, value in override.items():
        out[key] = _deep_merge(base[key], value) if isinstance(value, dict) and isinstance(base.get(key), dict) else value
    return out


def _simulation_config(args: argparse.Namespace):
    from data_catalog.textfiles import read_yaml_mapping
    from schemas.simulation import SimulationConfig
    from simulator.presets import preset_config

    base = preset_config(args.preset).model_dump()
    if args.config is not None:
        base = _deep_merge(base, read_yaml_mapping(args.config, "simulation config"))
    if args.seed is not None:
        base["seed"] = args.seed
    if args.sample_id is not None:
        base["sample_id"] = args.sample_id
    try:
        return SimulationConfig.model_validate(base)
    except ValidationError as exc:
        source = args.config or f"preset {args.preset}"
        raise ValueError(f"{source}: invalid simulation config:\n{_describe(exc)}") from None


def _cmd_simulate(args: argparse.Namespace) -> int:
    from simulator.run import simulate

    from data_catalog.atomic import check_can_create

    config = _simulation_config(args)
    out = Path(args.out_dir)
    if out.exists():
        raise ValueError(f"{out} already exists; choose a new folder (nothing was written)")
    check_can_create(out, f"OUT_DIR {out}")
    started = time.perf_counter()

    def progress(message: str) -> None:
        print(f"[{time.perf_counter() - started:7.1f} s] {message}", file=sys.stderr, flush=True)

    pace = _pace(args.pace) if args.pace is not None else None
    progress(f"simulating preset {config.preset!r} (seed {config.seed}) into {out}")
    summary = simulate(config, out, progress=progress, previews=not args.no_preview, pace=pace)
    print(f"{summary.out_dir}: {summary.n_passes} passes, {summary.n_points:,} points "
          f"({summary.n_valid_points:,} returns), {summary.n_stickers_specimen} stickers on the specimen, "
          f"{summary.n_stickers_fixture} on the fixture, {summary.seconds:.1f} s")
    if not args.no_preview:
        print(f"pictures: {summary.out_dir / 'preview'}")
    return 0


def _pace(text: str) -> float:
    """``realtime`` (the robot's own speed) or ``xN`` (N times faster) as a speed-up factor."""
    if text == "realtime":
        return 1.0
    try:
        factor = float(text[1:]) if text.startswith("x") else float("nan")
    except ValueError:
        factor = float("nan")
    if not factor > 0:
        raise ValueError(f"--pace {text!r}: expected realtime or xN with N > 0 (x10: ten times the robot's speed)")
    return factor


def _quiet_prefect() -> None:
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")


_LOG_FILE: Path | None = None


def _log_path(folder: Path, name: str) -> Path:
    """A new log file's name in ``folder``: the command, UTC time and process id."""
    from datetime import UTC, datetime

    return folder / f"{name}-{datetime.now(UTC).strftime('%Y%m%dT%H%M%SZ')}-{os.getpid()}.log"


def _log_to_file(folder: Path, name: str) -> Path:
    """Send Prefect's and the libraries' log records (tracebacks included) to a log file in
    ``folder`` instead of the terminal, which gets one line per problem; returns the file."""
    import logging

    from prefect.logging.configuration import setup_logging

    global _LOG_FILE
    setup_logging()  # Prefect's own configuration first (later calls only adjust it)
    folder.mkdir(parents=True, exist_ok=True)
    path = _log_path(folder, name)
    handler = logging.FileHandler(path, encoding="utf-8", delay=True)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s %(threadName)s: %(message)s"))
    loggers = [lg for lg in list(logging.root.manager.loggerDict.values()) if isinstance(lg, logging.Logger)]
    for logger in [logging.getLogger(), *loggers]:
        for old in [h for h in logger.handlers if type(h).__name__ == "PrefectConsoleHandler"]:
            logger.removeHandler(old)
            logger.addHandler(handler)
    logging.getLogger().setLevel(logging.INFO)
    logging.captureWarnings(True)
    _LOG_FILE = path
    return path


def _print_report(run, out: Path) -> None:
    """The run's summary on the terminal (``run``: a ``flows.reconstruct.RunResult``)."""
    from flows.stages import STAGES

    report = run.report
    refined, mesh = report.stages["refine"], report.mesh
    print(f"{report.sample_id}: {len(report.passes)} passes")
    for stage in STAGES:
        name = stage.name
        if name not in report.stages:
            continue
        value, seconds, cached = report.stages[name], run.seconds.get(name, 0.0), run.cached[name]
        if stage.per_pass:
            print(f"  {name:<12} {len(value)} passes, {seconds:.1f} s of work{', all cached' if cached else ''}")
        else:
            extra = {k: (round(v, 4) if isinstance(v, float) else v) for k, v in value.items()
                     if k in ("points_in", "points_out", "residual_median_mm", "residual_max_mm", "vertices",
                              "watertight", "surface_pairs", "surface_rms_median_mm", "largest_pose_change_mm",
                              "target_residual_median_mm")}
            print(f"  {name:<12} {'cached' if cached else f'{seconds:.1f} s'}  {extra}")
    methods = report.registration_method
    if methods:  # per pass: targets, surfaces from given poses, surfaces, global
        kinds = sorted(set(methods.values()))
        print("registration: " + "; ".join(f"{k} ({sum(v == k for v in methods.values())} passes)" for k in kinds))
    weak = report.registration.pairs_below_min_common
    if weak:
        print("  pass pairs with fewer common targets than needed: "
              + ", ".join(f"{w.a}|{w.b} ({w.common_targets})" for w in weak))
    residual = refined.get("target_residual_median_mm")
    print(f"mesh: {mesh['vertices']:,} vertices, {mesh['triangles']:,} triangles, "
          f"{'watertight' if mesh['watertight'] else 'NOT watertight'}"
          + (f"; target residual median {residual * 1000:.0f} um, max {refined['target_residual_max_mm'] * 1000:.0f} um"
             if residual is not None else ""))
    weld = report.weld
    if weld.measured:
        failing = weld.failing_sections
        print(f"weld: {weld.sections_measured} of {weld.sections} sections measured, {weld.verdict} against "
              f"the acceptance limits" + (f" ({len(failing)} findings in {weld.failing} sections: report.json, "
                                          f"'weld')" if failing else "")
              + (f"; {weld.sections_uncertain} sections uncertain (a figure within its 1-sigma of a limit)"
                 if weld.sections_uncertain else ""))
    else:
        print(f"weld: not measured: {weld.why_not}")
    volume = report.volume_mesh
    if volume.made:
        solid, quality = volume.solid, volume.quality
        print(f"FE model: {solid.tetrahedra:,} tetrahedra, one solid, volume {100 * solid.volume_difference:+.2f} % "
              f"of the mesh's; worst element: dihedral {quality.min_dihedral_deg.worst:.1f} deg, "
              f"aspect ratio {quality.aspect_ratio.worst:.1f}")
    else:
        print(f"FE model: not made: {volume.why}")
    for item in run.outputs.values():
        print(f"  {item['path']}")
    if "report.html" in run.outputs:
        print(f"QA report: {run.outputs['report.html']['path']} (one file, opens offline in a browser)")
    head = run.trail_head  # the anchor: keep it outside the run folder; `audit verify --head` checks the trail still holds it
    print(f"audit trail head: seq {head.seq} sha256 {head.hash} (weldrecon audit verify {out} --head {head.hash})")
    checks = report.checks
    flagged = [c for c in checks if c.result != "ok"]
    print(f"checks: {len(checks) - len(flagged)} of {len(checks)} ok (report.json, 'checks')")
    for c in flagged:
        print(f"weldrecon reconstruct: warning: pass {c.pass_}: {c.check}: {c.what}", file=sys.stderr)


def _cmd_reconstruct(args: argparse.Namespace) -> int:
    _quiet_prefect()
    import getpass

    from data_catalog.manifests import check_sample_files, load_manifest
    from flows.preflight import check_dask_scheduler, check_out_dir, check_run_folder, load_config, wait_for_file

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
    load_config(args.config)
    check_run_folder(out, manifest.sample_id)
    stop_after = getattr(args, "stop_after", None)
    if stop_after is not None:
        from flows.stages import STAGE_NAMES

        if stop_after not in STAGE_NAMES:
            raise ValueError(f"--stop-after {stop_after}: no such stage; the stages are {', '.join(STAGE_NAMES)}")
    dask = getattr(args, "dask", None) or os.environ.get("WELDRECON_DASK") or None
    if dask and not dask.startswith("local:"):
        check_dask_scheduler(dask)
    from flows.progress import TrailProgress
    from flows.reconstruct import prefect_api_for_workers, reconstruct_sample
    from flows.stages import STAGES

    _log_to_file(out / "logs", "reconstruct")
    n_passes = len(manifest.passes())
    upto = STAGES[:[s.name for s in STAGES].index(stop_after) + 1] if stop_after else STAGES
    expected = [(s.name, n_passes if s.per_pass else 1) for s in upto]
    with contextlib.ExitStack() as stack:
        # the run's own temporary API server, which the kernel stops if this process dies
        # (Prefect's own would outlive a kill -9); Dask workers report to it too
        api = stack.enter_context(prefect_api_for_workers())
        if dask:
            print(f"Dask workers report to the Prefect API at {api}", file=sys.stderr, flush=True)
        stack.enter_context(TrailProgress(out, expected, stream=sys.stderr))
        run = reconstruct_sample(str(sample), str(out), args.config, started_by=f"cli ({getpass.getuser()})",
                                 dask=dask, follow_timeout_s=follow, stop_after=stop_after)
    if run.report is None:
        print(f"stopped after stage {stop_after}: " + ", ".join(f"{n} ({'cached' if run.cached[n] else f'{run.seconds[n]:.1f} s'})"
                                                          for n in run.refs) + f"; nothing published in {out}")
        return 0
    _print_report(run, out)
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from simulator.presets import preset_config
    from simulator.run import simulate

    from data_catalog.atomic import check_can_create

    root = Path(args.out)
    check_can_create(root, f"--out {root}")
    sample = root / "sample"
    if not sample.exists():
        started = time.perf_counter()
        print(f"simulating the demo sample into {sample} ...", file=sys.stderr, flush=True)
        summary = simulate(preset_config("demo"), sample)
        print(f"  {summary.n_passes} passes, {summary.n_points:,} points, {time.perf_counter() - started:.0f} s",
              file=sys.stderr)
    config = Path(__file__).resolve().parents[1] / "deploy" / "configs" / "demo.yaml"
    args = argparse.Namespace(sample_dir=str(sample), out=str(root / "reconstruction"),
                              config=str(config) if config.is_file() else None)
    print("reconstructing ...", file=sys.stderr, flush=True)
    return _cmd_reconstruct(args)


def _cmd_import(args: argparse.Namespace) -> int:
    from data_catalog.atomic import check_can_create
    from data_catalog.cell_logs import import_cell

    out = Path(args.out_sample)
    if out.exists():
        raise ValueError(f"{out} already exists; choose a new folder (nothing was written)")
    check_can_create(out, f"OUT_SAMPLE {out}")
    summary = import_cell(args.cell_yaml, out)
    print(f"{summary.out_dir}: {summary.n_passes} passes, {summary.n_profiles:,} profiles, {summary.n_points:,} points")
    return 0


def _cmd_import_scans(args: argparse.Namespace) -> int:
    from data_catalog.atomic import check_can_create
    from data_catalog.scan_import import import_scans

    out = Path(args.out_sample)
    if out.exists():
        raise ValueError(f"{out} already exists; choose a new folder (nothing was written)")
    check_can_create(out, f"OUT_SAMPLE {out}")
    try:
        view = tuple(float(v) for v in args.view_direction.split(","))
    except ValueError:
        view = args.view_direction
    summary = import_scans(args.files, out, units=args.units, poses=args.poses, ignore_poses=args.ignore_poses,
                           sample_id=args.sample_id, view_direction=view)
    print(f"{summary.out_dir}: {summary.n_scans} scans, {summary.n_points:,} points, "
          f"{'poses given' if summary.with_poses else 'no poses (the registration finds them)'}; "
          f"registration: surfaces")
    return 0


def _no_return(text: str) -> str | float:
    """``--no-return``: nan, empty or a number."""
    if text in ("nan", "empty"):
        return text
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"--no-return {text!r}: expected nan, empty or a number (such as 0 or -9999)") from None


def _cmd_export_cell(args: argparse.Namespace) -> int:
    from simulator.export_cell import export_cell

    from data_catalog.atomic import check_can_create

    out = Path(args.out_dir)
    if out.exists():
        raise ValueError(f"{out} already exists; choose a new folder (nothing was written)")
    check_can_create(out, f"OUT_DIR {out}")
    summary = export_cell(args.sample_dir, out, layout=args.layout, delimiter=args.delimiter, compress=args.gzip,
                          orientation=args.orientation, quaternion_order=args.quaternion_order,
                          angle_unit=args.angle_unit, units=args.units, time_unit=args.time_unit,
                          no_return=_no_return(args.no_return), intensity_bits=args.intensity_bits,
                          pose_every=args.pose_every, time_offset_s=args.time_offset)
    print(f"{summary.out_dir}: {summary.n_passes} passes, {summary.n_profiles:,} profiles, {summary.n_poses:,} poses; "
          f"weldrecon import {summary.out_dir / 'CELL.yaml'} SAMPLE")
    return 0


def _cmd_stages(args: argparse.Namespace) -> int:
    from flows.stages import stage_table

    sys.stdout.write(stage_table())
    return 0


def _cmd_schema(args: argparse.Namespace) -> int:
    from data_catalog.manifests import manifest_json_schema

    sys.stdout.write(manifest_json_schema())
    return 0


def _workspace(args: argparse.Namespace) -> Path:
    return Path(args.workspace or os.environ.get("WELDRECON_WORKSPACE", "workspace"))


def _say_displaced(catalog, records) -> None:
    """One line per catalogued sample whose folder a just-registered sample now occupies (renamed,
    or the folder reused): it is not rebuilt from the new data, and the user should know."""
    folders = {r.sample_dir: r.sample_id for r in records}
    for other in catalog.list():
        if other.sample_dir in folders and other.sample_id != folders[other.sample_dir]:
            print(f"weldrecon catalog: warning: sample {other.sample_id}: failed at register: {other.error}",
                  file=sys.stderr)


def _cmd_catalog(args: argparse.Namespace) -> int:
    from data_catalog.catalog import Catalog, CatalogError

    catalog = Catalog(_workspace(args))
    if args.action == "register":
        status = 0
        for path in args.paths:  # one bad path is named; the others are still registered
            folder = Path(path)
            try:
                if (folder / "manifest.json").exists():
                    record = catalog.register(folder)
                    print(f"{record.sample_id}: {record.state}"
                          f"{' (changed)' if record.due and record.state == 'done' else ''}")
                    _say_displaced(catalog, [record])
                    continue
                records, refused = catalog.scan(folder)
                _say_displaced(catalog, records)
            except CatalogError:
                raise
            except (ValueError, OSError) as exc:
                records, refused = [], [f"{folder}: {exc}" if str(folder) not in str(exc) else str(exc)]
            else:
                if not records and not refused:
                    refused = [f"{folder}: no sample folder (one holding manifest.json) in it or under it"]
            for record in records:
                print(f"{record.sample_id}: {record.state}")
            for line in refused:
                print(f"not registered: {line}", file=sys.stderr)
                status = 2
        return status
    if args.action == "index":
        from flows.qa_index import write_index

        print(f"index: {write_index(catalog.workspace)}")
        return 0
    if args.action == "list":
        records = catalog.list()
        if not records:
            print(f"no samples in {catalog.path}")
        for r in records:
            state = r.state + (f" at {r.failed_stage}" if r.state == "failed" and r.failed_stage else "")
            if r.state == "done" and r.due:
                state += " (changed since)"
            print(f"{r.sample_id:<24} {state:<28} {r.updated}  {r.sample_dir}")
        return 0
    record = catalog.get(args.sample)
    print(f"sample      {record.sample_id}")
    print(f"folder      {record.sample_dir}")
    print(f"state       {record.state}" + (f" at stage {record.failed_stage}" if record.failed_stage else ""))
    if record.error:
        print(f"error       {record.error}")
    print(f"fingerprint {record.fingerprint}" + ("" if not record.done_fingerprint or not record.due else
                                                 f" (last done with {record.done_fingerprint[:12]}…)"))
    print(f"run folder  {record.out_dir or '-'}")
    print(f"registered  {record.registered}   updated {record.updated}")
    for name, digest in sorted(record.artefacts.items()):
        print(f"  {name}  sha256 {digest}")
    return 0


def _run_folder(args: argparse.Namespace) -> tuple[Path, dict[str, str]]:
    """A run folder given directly, or a sample id looked up in the catalog; and the trail heads
    kept outside it (the catalog's, for a catalogued run folder; ``--head``) -> where kept."""
    from data_catalog.catalog import CATALOG_NAME, Catalog

    target = Path(args.target)
    workspace = _workspace(args)
    catalog = Catalog(workspace) if (workspace / CATALOG_NAME).is_file() else None  # looking must not create one
    head = getattr(args, "head", None)
    if head is not None and not re.fullmatch(r"[0-9a-f]{64}", head):
        raise ValueError(f"--head {head}: expected an entry's sha256 (64 hex digits), as reconstruct prints it")
    heads = {head: "--head"} if head else {}
    if target.is_dir():
        folder = target
        records = [r for r in catalog.list() if r.out_dir and Path(r.out_dir).resolve() == folder.resolve()] \
            if catalog else []
    elif catalog is None:
        raise FileNotFoundError(f"{args.target}: not a run folder, and no catalog at {workspace / CATALOG_NAME} "
                                "to look it up in as a sample id (--workspace)")
    else:
        records = [catalog.get(args.target)]
        if not records[0].out_dir:
            raise ValueError(f"sample {args.target} has not been reconstructed yet")
        folder = Path(records[0].out_dir)
    for record in records:
        if record.trail_head:
            heads[record.trail_head["hash"]] = (f"the catalog {catalog.path} (sample {record.sample_id}, its last "
                                                f"finished run, seq {record.trail_head['seq']})")
    return folder, heads


def _cmd_audit(args: argparse.Namespace) -> int:
    import json

    from data_catalog.audit import read_trail, verify_trail

    folder, heads = _run_folder(args)
    if args.action == "verify":
        problems = verify_trail(folder, heads=heads)
        entries = read_trail(folder)
        if problems:
            print(f"{folder}: audit trail NOT intact ({len(problems)} problem(s)):")
            for problem in problems:
                print(f"  {problem}")
            return 1
        n_artefacts = len({k for e in entries for k in (e.get("artefacts") or {})})
        anchored = (f", holds the head{'s' if len(heads) > 1 else ''} kept by " + "; ".join(heads.values())
                    if heads else ", no head kept outside the folder to compare (catalog, --head)")
        print(f"{folder}: audit trail intact: {len(entries)} entries chained, {n_artefacts} artefacts re-hashed"
              + anchored)
        return 0
    for e in read_trail(folder):
        if "_unreadable" in e:
            print(f"   ?  unreadable: {e['_unreadable']}")
            continue
        head = f"{e['seq']:>4}  {e['time'][:19]}  {e['kind']:<17}"
        if e["kind"] == "run-started":
            print(f"{head} {e.get('sample_id')} by {e.get('started_by')}, flow run {e.get('flow_run_id')}"
                  + (f", deployment {e.get('deployment_name')}" if e.get("deployment_name") else ""))
        elif e["kind"] == "stage":
            record = e.get("record") or {}
            took = "reused" if e.get("cached") else f"{(record.get('metrics') or {}).get('seconds', '?')} s"
            what = e["stage"] + (f" {e['item']}" if e.get("item") else "")
            print(f"{head} {what:<22} {took:<9} key {e['cache_key'][:12]}  code {record.get('code_version')}  "
                  f"host {record.get('host')}")
        elif e["kind"] == "run-finished":
            print(f"{head} " + ", ".join(f"{k} {v[:12]}" for k, v in (e.get("artefacts") or {}).items()))
        elif e["kind"] in ("run-failed", "stage-failed"):
            what = (e.get("stage") or "?") + (f" {e['item']}" if e.get("item") else "")
            print(f"{head} at {what}: {e.get('error')}")
        else:
            print(f"{head} " + json.dumps({k: v for k, v in e.items() if k not in ("seq", "time", "kind", "hash", "prev")}))
    return 0


def _cmd_batch(args: argparse.Namespace) -> int:
    _quiet_prefect()
    from data_catalog.catalog import Catalog

    workspace = _workspace(args)
    Catalog(workspace)  # a damaged catalog is named before any flow runs
    if args.config is not None:
        from flows.preflight import load_config

        load_config(args.config)
    from flows.batch import reconstruct_batch

    log = _log_to_file(workspace / "logs", "batch")
    print(f"batch log: {log}", file=sys.stderr)
    summary = reconstruct_batch(str(workspace), args.samples, args.config, args.max_concurrent,
                                started_by="cli batch")
    print(f"done: {', '.join(summary['done']) or 'none'}")
    for sample_id, why in summary["failed"].items():
        print(f"FAILED {sample_id} at {why['stage']}: {why['error']}")
    for line in summary["not_registered"]:
        print(f"NOT REGISTERED {line}")
    print(f"up to date: {', '.join(summary['up_to_date']) or 'none'}")
    if summary.get("index"):
        print(f"index: {summary['index']}")
    return 1 if summary["failed"] or summary["not_registered"] else 0


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="weldrecon", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    sim = sub.add_parser("simulate", help="simulate a scanning cell's output for one sample")
    sim.add_argument("out_dir", metavar="OUT_DIR", help="new folder for the sample (must not exist)")
    sim.add_argument("--preset", default="demo", help="ci, demo, paper, tjoint or tjoint-single (default: demo)")
    sim.add_argument("--config", metavar="FILE", help="YAML file of fields that override the preset")
    sim.add_argument("--seed", type=int, help="override the preset's seed")
    sim.add_argument("--sample-id", help="override the preset's sample id")
    sim.add_argument("--no-preview", action="store_true", help="skip the PNG pictures")
    sim.add_argument("--pace", metavar="realtime|xN", help="write the manifest first, then each pass when the robot "
                     "would have finished it, at its speed (realtime) or N times faster (xN): for --follow")
    sim.set_defaults(func=_cmd_simulate)
    rec = sub.add_parser("reconstruct", help="registered point cloud and watertight STL of one sample")
    rec.add_argument("sample_dir", metavar="SAMPLE_DIR", help="folder with manifest.json and the passes")
    rec.add_argument("--config", metavar="FILE", help="YAML file of reconstruction settings (schemas/reconstruction.py)")
    rec.add_argument("--out", metavar="DIR", help="output folder (default: SAMPLE_DIR-reconstruction beside it)")
    rec.add_argument("--dask", metavar="ADDRESS", help="run the per-pass work on a Dask cluster: a scheduler "
                                                       "address, or local:N for N local worker processes "
                                                       "(default: $WELDRECON_DASK, else threads here)")
    rec.add_argument("--stop-after", metavar="STAGE", help="run the stages up to and including STAGE (see "
                     "`weldrecon stages`) and stop; nothing is published")
    rec.add_argument("--follow", action="store_true", help="follow a scan in progress: start each pass's stages as "
                     "soon as its store is complete on disk (the manifest may come first)")
    rec.add_argument("--follow-timeout", type=float, default=1800.0, metavar="S",
                     help="with --follow: longest wait for the manifest and for each next pass (default 1800 s)")
    rec.set_defaults(func=_cmd_reconstruct)
    demo = sub.add_parser("demo", help="simulate the demo sample (once) and reconstruct it")
    demo.add_argument("--out", default="out/demo", help="folder for the sample and its reconstruction")
    demo.set_defaults(func=_cmd_demo)
    ws = argparse.ArgumentParser(add_help=False)
    ws.add_argument("--workspace", metavar="DIR", help="catalog and run folders (default: $WELDRECON_WORKSPACE "
                                                       "or ./workspace)")
    cat = sub.add_parser("catalog", help="the sample catalog: register, list, show, index")
    cat_sub = cat.add_subparsers(dest="action", required=True)
    reg = cat_sub.add_parser("register", parents=[ws], help="register sample folders, or every sample under a folder")
    reg.add_argument("paths", nargs="+", metavar="PATH")
    cat_sub.add_parser("list", parents=[ws], help="every sample and its state")
    show = cat_sub.add_parser("show", parents=[ws], help="one sample: state, run folder, artefacts and hashes")
    show.add_argument("sample", metavar="SAMPLE")
    cat_sub.add_parser("index", parents=[ws], help="write WORKSPACE/index.html: every sample, its verdicts and a "
                                                   "link to its QA report (a batch writes it too)")
    cat.set_defaults(func=_cmd_catalog)
    batch = sub.add_parser("batch", parents=[ws], help="reconstruct every new, failed or changed sample")
    batch.add_argument("--samples", metavar="DIR", help="register the sample folders under DIR first")
    batch.add_argument("--config", metavar="FILE", help="YAML file of reconstruction settings")
    batch.add_argument("--max-concurrent", type=int, default=1, help="samples reconstructed at once (default 1)")
    batch.set_defaults(func=_cmd_batch)
    aud = sub.add_parser("audit", help="a sample's audit trail: verify it, or show it")
    aud_sub = aud.add_subparsers(dest="action", required=True)
    for action, text in (("verify", "re-hash the chain and every recorded artefact; say what differs"),
                         ("show", "print the trail readably")):
        a = aud_sub.add_parser(action, parents=[ws], help=text)
        a.add_argument("target", metavar="SAMPLE", help="a sample id in the catalog, or a run folder")
        if action == "verify":
            a.add_argument("--head", metavar="SHA256", help="an entry hash kept outside the folder (printed by "
                           "reconstruct as the audit trail head): the trail must still hold it")
    aud.set_defaults(func=_cmd_audit)
    imp = sub.add_parser("import", help="a real cell's logs (profile files, pose logs, CELL.yaml) into a sample folder")
    imp.add_argument("cell_yaml", metavar="CELL.yaml", help="the cell description (docs/cell-logs.md)")
    imp.add_argument("out_sample", metavar="OUT_SAMPLE", help="new folder for the sample (must not exist)")
    imp.set_defaults(func=_cmd_import)
    isc = sub.add_parser("import-scans", help="point clouds of any scanner (PLY, PCD, XYZ/CSV/TXT, E57, LAS/LAZ) into a "
                         "sample registered on its surfaces (docs/point-clouds.md)")
    isc.add_argument("out_sample", metavar="OUT_SAMPLE", help="new folder for the sample (must not exist)")
    isc.add_argument("files", nargs="+", metavar="FILE", help="the scans, one pass each (an E57 file: one per scan in it)")
    isc.add_argument("--units", metavar="mm|cm|m|in", help="length unit of the files' coordinates and of the .conf "
                     "(required but for E57, metres by its standard)")
    isc.add_argument("--poses", metavar="FILE.conf", help="the scans' poses: a Stanford/scanalyze .conf "
                     "(bmesh FILE tx ty tz qx qy qz qw), one line per scan given")
    isc.add_argument("--ignore-poses", action="store_true", help="use no pose (not the E57 files' own): the "
                     "registration finds them")
    isc.add_argument("--sample-id", help="the sample's id (default: OUT_SAMPLE's name)")
    isc.add_argument("--view-direction", default="0,0,1", metavar="x,y,z", help="from the surface toward the scanner "
                     "in each scan's frame (normals are turned toward it; default 0,0,1)")
    isc.set_defaults(func=_cmd_import_scans)
    exp = sub.add_parser("export-cell", help="write a sample (with flange poses per profile) as cell logs + CELL.yaml")
    exp.add_argument("sample_dir", metavar="SAMPLE", help="folder with manifest.json and the passes")
    exp.add_argument("out_dir", metavar="OUT_DIR", help="new folder for CELL.yaml and the logs (must not exist)")
    exp.add_argument("--layout", choices=("xzi", "z_grid"), default="xzi", help="profile layout (default xzi)")
    exp.add_argument("--delimiter", choices=("csv", "whitespace"), default="csv")
    exp.add_argument("--gzip", action="store_true", help="gzip the profile files")
    exp.add_argument("--orientation", default="quaternion", help="rotation convention of the pose log: quaternion, "
                     "rotation-vector, kuka-abc, fanuc-wpr or euler-<AXES>-<intrinsic|extrinsic> (default quaternion)")
    exp.add_argument("--quaternion-order", choices=("wxyz", "xyzw"), default="wxyz")
    exp.add_argument("--angle-unit", choices=("deg", "rad"), help="for rotation-vector and euler-*")
    exp.add_argument("--units", choices=("mm", "m"), default="mm", help="length unit of both files (default mm)")
    exp.add_argument("--time-unit", choices=("s", "ms"), default="s")
    exp.add_argument("--no-return", default="nan", metavar="nan|empty|NUMBER", help="marker of a missing return")
    exp.add_argument("--intensity-bits", type=int, default=10, help="bit depth of the written intensities (default 10)")
    exp.add_argument("--pose-every", type=int, default=3, metavar="N", help="a pose for every N-th profile (default 3)")
    exp.add_argument("--time-offset", type=float, default=0.0, metavar="S",
                     help="the robot's clock minus the scanner's, s (default 0)")
    exp.set_defaults(func=_cmd_export_cell)
    stages = sub.add_parser("stages", help="print the reconstruction's stages: inputs, settings, outputs")
    stages.set_defaults(func=_cmd_stages)
    schema = sub.add_parser("schema", help="print the sample manifest's JSON schema")
    schema.set_defaults(func=_cmd_schema)
    return parser


def _traceback_log(command: str, exc: BaseException) -> Path | None:
    """Where the traceback of a failure goes: the run's log file when the command opened one,
    else a file under $WELDRECON_LOG_DIR (default ~/.local/state/weldrecon/logs); None if
    neither can be written (a full disk: the one line must still reach the terminal)."""
    import logging
    import traceback

    if _LOG_FILE is not None:
        logging.getLogger("weldrecon").error("%s failed", command, exc_info=exc)
        return _LOG_FILE
    folder = Path(os.environ.get("WELDRECON_LOG_DIR") or Path.home() / ".local" / "state" / "weldrecon" / "logs")
    path = _log_path(folder, command)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        path.write_text("".join(traceback.format_exception(exc)), encoding="utf-8")
    except OSError:
        return None
    return path


def main(argv: list[str] | None = None) -> int:
    import signal
    import sqlite3

    signal.signal(signal.SIGPIPE, signal.SIG_DFL)  # `weldrecon audit show X | head` ends quietly
    args = _parser().parse_args(argv)
    try:
        return args.func(args)
    except KeyboardInterrupt:
        print(f"weldrecon {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - one line on the terminal, the traceback in a log file
        if isinstance(exc, KeyError):
            what = exc.args[0] if exc.args else exc
        elif isinstance(exc, (ValueError, OSError, RuntimeError, TimeoutError, sqlite3.Error)):
            stage = getattr(exc, "stage", None)
            what = (f"stage {stage}: " if stage and not str(exc).startswith(f"stage {stage}") else "") + str(exc)
        elif isinstance(exc, MemoryError):
            what = f"out of memory ({exc or 'no detail'}); give the run more memory or smaller blocks"
        else:  # not an input problem we know of: say so, and keep the evidence
            what = f"unexpected {type(exc).__name__}: {exc} (please report it with the log below)"
        print(f"weldrecon {args.command}: error: {what}", file=sys.stderr)
        plain = (KeyError, ValueError, FileNotFoundError, FileExistsError, TimeoutError)  # input errors we name
        if _LOG_FILE is not None or not isinstance(exc, plain):
            log = _traceback_log(args.command, exc)
            if log is not None:
                print(f"  (the details and the traceback: {log})", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
