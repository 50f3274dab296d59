"""The sample's audit trail: an append-only, hash-chained log of everything done to its data.

``<run folder>/audit/trail.jsonl``, one JSON object per line::

    {"seq": 0, "prev": "000…0", "time": ..., "kind": "run-started", ..., "hash": sha256}

Each entry's ``hash`` is the sha256 of its canonical JSON without the ``hash`` field, and each
``prev`` is the hash of the entry before: editing, inserting, dropping or reordering a line breaks
the chain at that line. Entries that name artefacts (stage outputs, results) carry their content
hashes, so ``verify`` re-hashes the artefacts too and says which one changed.

Kinds: ``run-started`` (who/what started the run: CLI, deployment, schedule; Prefect run ids),
``stage`` (a stage's provenance record: inputs, outputs, parameters, code version, host, times;
``cached`` when the outputs were reused), ``stage-recomputed`` (a cached artefact failed its hash
and was set aside), ``run-finished`` / ``run-failed``.

Appends from the flow's worker threads and processes are serialised by an exclusive lock on the
trail file.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from data_catalog.hashing import sha256_tree

__all__ = ["TRAIL", "append", "read_trail", "AuditProblem", "verify_trail", "GENESIS"]

TRAIL = Path("audit") / "trail.jsonl"
GENESIS = "0" * 64


def _digest(entry: dict[str, Any]) -> str:
    body = {k: v for k, v in entry.items() if k != "hash"}
    return hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":"), default=str).encode()).hexdigest()


def append(run_dir: Path, kind: str, **fields: Any) -> dict[str, Any]:
    """Append one entry to the run folder's trail (created on first use); returns it."""
    path = Path(run_dir) / TRAIL
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a+", encoding="utf-8") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            handle.seek(0)
            last = None
            for line in handle:
                if line.strip():
                    last = line
            prev = json.loads(last) if last else None
            entry = {"seq": 0 if prev is None else prev["seq"] + 1, "prev": GENESIS if prev is None else prev["hash"],
                     "time": datetime.now(UTC).isoformat(), "kind": kind, **fields}
            entry["hash"] = _digest(entry)
            handle.seek(0, os.SEEK_END)
            handle.write(json.dumps(entry, sort_keys=True, default=str) + "\n")
            handle.flush()
            os.fsync(handle.fileno())
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)
    return entry


def read_trail(run_dir: Path) -> list[dict[str, Any]]:
    path = Path(run_dir) / TRAIL
    if not path.is_file():
        raise FileNotFoundError(f"{run_dir}: no audit trail ({TRAIL}) there")
    entries = []
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        if not line.strip():
            continue
        try:
            entries.append(json.loads(line))
        except json.JSONDecodeError as exc:
            entries.append({"_unreadable": f"line {number}: {exc.msg}", "_line": number})
    return entries


@dataclass(frozen=True)
class AuditProblem:
    where: str  # "trail line 7 (seq 6)" or an artefact path
    what: str

    def __str__(self) -> str:
        return f"{self.where}: {self.what}"


def _artefacts(entry: dict[str, Any]) -> dict[str, str]:
    """Artefact path -> sha256 recorded by this entry."""
    return dict(entry.get("artefacts") or {})


def verify_trail(run_dir: Path, *, artefacts: bool = True) -> list[AuditProblem]:
    """Every break in the chain, and (with ``artefacts``) every recorded artefact whose content no
    longer matches: the latest entry naming a path decides what it should hold. Empty: intact."""
    run_dir = Path(run_dir)
    problems: list[AuditProblem] = []
    prev = GENESIS
    expected: dict[str, tuple[str, int]] = {}
    for number, entry in enumerate(read_trail(run_dir), start=1):
        where = f"trail line {number}"
        if "_unreadable" in entry:
            problems.append(AuditProblem(where, f"not valid JSON ({entry['_unreadable']})"))
            prev = None
            continue
        where = f"trail line {number} (seq {entry.get('seq')}, {entry.get('kind')})"
        if entry.get("seq") != number - 1:
            problems.append(AuditProblem(where, f"sequence number {entry.get('seq')}, expected {number - 1} "
                                                "(a line was removed, inserted or moved)"))
        if _digest(entry) != entry.get("hash"):
            problems.append(AuditProblem(where, "its content does not match its hash (the entry was edited)"))
        if prev is not None and entry.get("prev") != prev:
            problems.append(AuditProblem(where, "does not chain to the entry before it (an entry before it "
                                                "was edited, removed or reordered)"))
        prev = entry.get("hash")
        for rel, digest in _artefacts(entry).items():
            expected[rel] = (digest, number)
    if artefacts:
        for rel, (digest, number) in sorted(expected.items()):
            path = run_dir / rel
            try:
                actual = sha256_tree(path)
            except FileNotFoundError:
                problems.append(AuditProblem(rel, f"missing (recorded at trail line {number})"))
                continue
            if actual != digest:
                problems.append(AuditProblem(rel, f"content changed: sha256 {actual[:12]}…, the trail (line {number}) "
                                                  f"recorded {digest[:12]}…"))
    return problems
