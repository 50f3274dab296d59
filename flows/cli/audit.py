"""``weldrecon audit verify|show``: a run's audit trail, re-hashed against the heads kept outside
its folder, or printed readably."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from flows.cli.catalog import existing_catalog, workspace

__all__ = ["add_audit"]


def add_audit(sub, ws: argparse.ArgumentParser) -> None:
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


def _run_folder(args: argparse.Namespace) -> tuple[Path, dict[str, str]]:
    """A run folder given directly, or a sample id looked up in the catalog; and the trail heads
    kept outside it (the catalog's, for a catalogued run folder; ``--head``) -> where kept."""
    from data_catalog.catalog import CATALOG_NAME

    target = Path(args.target)
    root = workspace(args)
    catalog = existing_catalog(root)
    head = getattr(args, "head", None)
    if head is not None and not re.fullmatch(r"[0-9a-f]{64}", head):
        raise ValueError(f"--head {head}: expected an entry's sha256 (64 hex digits), as reconstruct prints it")
    heads = {head: "--head"} if head else {}
    if target.is_dir():
        folder = target
        records = catalog.runs_in(folder) if catalog else []
    elif catalog is None:
        raise FileNotFoundError(f"{args.target}: not a run folder, and no catalog at {root / CATALOG_NAME} "
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
    folder, heads = _run_folder(args)
    return _verify(folder, heads) if args.action == "verify" else _show(folder)


def _verify(folder: Path, heads: dict[str, str]) -> int:
    """The chain and every recorded artefact re-hashed; 1 (and each problem) if anything differs."""
    from data_catalog.audit import read_trail, verify_trail

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
    events = [e for e in entries if e.get("kind") in RECORDED_EVENTS]
    said = f"; {len(events)} event{'s' if len(events) != 1 else ''} recorded:" if events else ""
    print(f"{folder}: audit trail intact: {len(entries)} entries chained, {n_artefacts} artefacts re-hashed"
          + anchored + said)
    for e in events:  # intact means the record is whole, not that nothing happened: what it records is said
        print(f"  seq {e.get('seq')} {e.get('time', '')} {RECORDED_EVENTS[e['kind']](e)}")
    return 0


def _stage(e: dict) -> str:
    return f"stage {e.get('stage')}{' ' + str(e['item']) if e.get('item') else ''}"


# what a trail records that its reader must see even when the chain is whole (a run's finding that the
# trail was not intact is not among them: verify_trail reports it as a problem for good)
RECORDED_EVENTS = {
    "stage-recomputed": lambda e: f"{_stage(e)} recomputed: {e.get('reason', '')}",
    "leftovers-swept": lambda e: f"a run that died left {len(e.get('paths') or [])} half-written path(s), swept: "
                                 f"{', '.join((e.get('paths') or [])[:5])}",
    "stage-failed": lambda e: f"{_stage(e)} failed: {e.get('error', '')}",
}


def _show(folder: Path) -> int:
    """The trail, one line per entry."""
    import json

    from data_catalog.audit import read_trail

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
