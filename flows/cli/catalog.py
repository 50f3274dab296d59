"""``weldrecon catalog`` (register, list, show, index) and ``weldrecon batch``: the samples of a
workspace, and reconstructing those that are new, failed or changed."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from flows.cli.errors import log_to_file, quiet_prefect

__all__ = ["add_catalog", "add_batch", "workspace_option", "workspace"]


def workspace_option() -> argparse.ArgumentParser:
    """The ``--workspace`` option, as a parent parser of the commands that read the catalog."""
    ws = argparse.ArgumentParser(add_help=False)
    ws.add_argument("--workspace", metavar="DIR", help="catalog and run folders (default: $WELDRECON_WORKSPACE "
                                                       "or ./workspace)")
    return ws


def workspace(args: argparse.Namespace) -> Path:
    """The workspace folder: ``--workspace`` (where the command has it), else $WELDRECON_WORKSPACE,
    else ./workspace."""
    return Path(getattr(args, "workspace", None) or os.environ.get("WELDRECON_WORKSPACE", "workspace"))


def existing_catalog(root: Path):
    """The workspace ``root``'s catalog (data_catalog.catalog.Catalog), or None where it has none:
    looking must not create one."""
    from data_catalog.catalog import CATALOG_NAME, Catalog

    return Catalog(root) if (root / CATALOG_NAME).is_file() else None


def add_catalog(sub, ws: argparse.ArgumentParser) -> None:
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


def add_batch(sub, ws: argparse.ArgumentParser) -> None:
    batch = sub.add_parser("batch", parents=[ws], help="reconstruct every new, failed or changed sample")
    batch.add_argument("--samples", metavar="DIR", help="register the sample folders under DIR first")
    batch.add_argument("--config", metavar="FILE", help="YAML file of reconstruction settings")
    batch.add_argument("--max-concurrent", type=int, default=1, help="samples reconstructed at once (default 1)")
    batch.set_defaults(func=_cmd_batch)


def _say_displaced(catalog, records) -> None:
    """One line per catalogued sample whose folder a just-registered sample now occupies (renamed,
    or the folder reused): it is not rebuilt from the new data, and the user should know."""
    folders = {r.sample_dir: r.sample_id for r in records}
    for other in catalog.list():
        if other.sample_dir in folders and other.sample_id != folders[other.sample_dir]:
            print(f"weldrecon catalog: warning: sample {other.sample_id}: failed at register: {other.error}",
                  file=sys.stderr)


def _register(catalog, paths: list[str]) -> int:
    """``catalog register``: one bad path is named; the others are still registered."""
    from data_catalog.catalog import CatalogError

    status = 0
    for path in paths:
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


def _list(catalog) -> int:
    records = catalog.list()
    if not records:
        print(f"no samples in {catalog.path}")
    for r in records:
        state = r.state + (f" at {r.failed_stage}" if r.state == "failed" and r.failed_stage else "")
        if r.state == "done" and r.due:
            state += " (changed since)"
        print(f"{r.sample_id:<24} {state:<28} {r.updated}  {r.sample_dir}")
    return 0


def _show(catalog, sample_id: str) -> int:
    record = catalog.get(sample_id)
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


def _cmd_catalog(args: argparse.Namespace) -> int:
    from data_catalog.catalog import Catalog

    catalog = Catalog(workspace(args))
    if args.action == "register":
        return _register(catalog, args.paths)
    if args.action == "index":
        from flows.qa_index import write_index

        print(f"index: {write_index(catalog.workspace)}")
        return 0
    if args.action == "list":
        return _list(catalog)
    return _show(catalog, args.sample)


def _cmd_batch(args: argparse.Namespace) -> int:
    quiet_prefect()
    from data_catalog.catalog import Catalog

    folder = workspace(args)
    Catalog(folder)  # a damaged catalog is named before any flow runs
    if args.config is not None:
        from flows.preflight import load_config

        load_config(args.config)
    from flows.batch import reconstruct_batch
    from flows.reconstruct import prefect_api_for_workers

    log = log_to_file(folder / "logs", "batch")
    print(f"batch log: {log}", file=sys.stderr)
    # the batch's own temporary API server, waited for up to 2 minutes (Prefect's own ephemeral one
    # gives up after 20 s: on a loaded machine "Timed out while attempting to connect to ephemeral
    # Prefect API server", issue 28), and stopped by the kernel if this process dies
    with prefect_api_for_workers():
        summary = reconstruct_batch(str(folder), args.samples, args.config, args.max_concurrent,
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
