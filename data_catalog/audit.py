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
and was set aside), ``run-finished`` / ``run-failed`` / ``run-stopped`` (ended after a named stage,
nothing published).

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

__all__ = ["TRAIL", "PROBLEMS_FOUND", "append", "read_trail", "recorded", "AuditProblem", "TrailError", "verify_trail", "GENESIS"]

TRAIL = Path("audit") / "trail.jsonl"
PROBLEMS_FOUND = "trail-problems-found"  # a run found the trail not intact before it appended
GENESIS = "0" * 64


def _digest(entry: dict[str, Any]) -> str:
    body = {k: v for k, v in entry.items() if k != "hash"}
    return hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":"), default=str).encode()).hexdigest()


class TrailError(RuntimeError):
    """The trail could not be read or written; the message names the file, the line and the cause."""


@dataclass(frozen=True)
class _Line:
    number: int  # 1-based
    start: int  # byte offset
    raw: bytes
    entry: dict[str, Any] | None  # None: unreadable
    problem: str | None


def _parse(raw: bytes, number: int, start: int) -> _Line:
    if not raw.endswith(b"\n"):
        return _Line(number, start, raw, None, "no line end (the write was cut short)")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        return _Line(number, start, raw, None, f"not UTF-8 (byte {exc.start}: {raw[exc.start:exc.start + 1]!r})")
    try:
        entry = json.loads(text)
    except json.JSONDecodeError as exc:
        return _Line(number, start, raw, None, f"not valid JSON ({exc.msg}, column {exc.colno})")
    if not isinstance(entry, dict) or not isinstance(entry.get("hash"), str) or not isinstance(entry.get("seq"), int):
        return _Line(number, start, raw, None, "not a trail entry (no seq or hash)")
    return _Line(number, start, raw, entry, None)


def _lines(data: bytes) -> list[_Line]:
    out, start, number = [], 0, 0
    while start < len(data):
        end = data.find(b"\n", start)
        end = len(data) if end < 0 else end + 1
        number += 1
        if data[start:end].strip():
            out.append(_parse(data[start:end], number, start))
        start = end
    return out


def _set_aside(path: Path, handle, damaged: list[_Line]) -> dict[str, Any]:
    """Move a damaged tail (``damaged``: the last lines, none readable) out of the trail into
    ``audit/damaged/``, truncate the trail before it; the facts for the entry that records it."""
    first = damaged[0]
    data = b"".join(line.raw for line in damaged)
    folder = path.parent / "damaged"
    folder.mkdir(exist_ok=True)
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S%fZ")
    kept = folder / f"{stamp}-line{first.number}.bin"
    with open(kept, "wb") as out:
        out.write(data)
        out.flush()
        os.fsync(out.fileno())
    handle.truncate(first.start)
    handle.flush()
    os.fsync(handle.fileno())
    return {"lines": [line.number for line in damaged], "bytes": len(data),
            "sha256": hashlib.sha256(data).hexdigest(), "cause": first.problem,
            "kept_at": str(kept.relative_to(path.parent.parent))}


def append(run_dir: Path, kind: str, **fields: Any) -> dict[str, Any]:
    """Append one entry to the run folder's trail (created on first use); returns it.

    The entry is written with one ``write`` and synced; if the write fails (a full disk), the
    trail is cut back to where it was and TrailError says why. A damaged tail left by an earlier
    write that was cut short (the last lines unreadable: no line end, not UTF-8, not JSON) is moved
    to ``audit/damaged/`` and a ``trail-damage-set-aside`` entry records its lines, bytes, hash and
    cause before this entry; damage with readable entries after it is not a cut-short write, and
    TrailError names its line (``weldrecon audit verify`` shows the rest)."""
    path = Path(run_dir) / TRAIL
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        handle = open(path, "a+b")
    except OSError as exc:
        raise TrailError(f"{path}: cannot open the audit trail ({exc.strerror or exc})") from exc
    with handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            handle.seek(0)
            lines = _lines(handle.read())
            good = [line for line in lines if line.entry is not None]
            bad = [line for line in lines if line.entry is None]
            pending = []
            if bad:
                if good and good[-1].number > bad[0].number:
                    raise TrailError(f"{path} line {bad[0].number}: {bad[0].problem}, with readable entries after "
                                     "it; not a cut-short write: the trail was damaged or edited")
                try:
                    facts = _set_aside(path, handle, bad)
                except OSError as exc:
                    raise TrailError(f"{path} line {bad[0].number}: {bad[0].problem}; could not set it aside "
                                     f"({exc.strerror or exc})") from exc
                pending.append(("trail-damage-set-aside", facts))
            pending.append((kind, fields))
            prev = good[-1].entry if good else None
            for entry_kind, entry_fields in pending:
                entry = {"seq": 0 if prev is None else prev["seq"] + 1,
                         "prev": GENESIS if prev is None else prev["hash"],
                         "time": datetime.now(UTC).isoformat(), "kind": entry_kind, **entry_fields}
                entry["hash"] = _digest(entry)
                _write_line(path, handle, (json.dumps(entry, sort_keys=True, default=str) + "\n").encode("utf-8"))
                prev = entry
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)
    return entry


def _write_line(path: Path, handle, data: bytes) -> None:
    handle.seek(0, os.SEEK_END)
    size = handle.tell()
    try:
        handle.write(data)
        handle.flush()
        os.fsync(handle.fileno())
    except OSError as exc:
        try:  # nothing half written stays in the trail
            handle.truncate(size)
            handle.flush()
        except OSError:
            pass
        raise TrailError(f"{path}: could not append an audit entry ({exc.strerror or exc}); the trail is as it "
                         "was before") from exc


def read_trail(run_dir: Path) -> list[dict[str, Any]]:
    """Every entry of the trail, in order; an unreadable line comes as ``{"_unreadable": why,
    "_line": number}``."""
    path = Path(run_dir) / TRAIL
    if not path.is_file():
        raise FileNotFoundError(f"{run_dir}: no audit trail ({TRAIL}) there")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise TrailError(f"{path}: cannot read the audit trail ({exc.strerror or exc})") from exc
    return [line.entry if line.entry is not None else {"_unreadable": f"line {line.number}: {line.problem}",
                                                         "_line": line.number}
            for line in _lines(data)]


@dataclass(frozen=True)
class AuditProblem:
    """One thing wrong with a run folder's trail or artefacts: ``where`` ("trail line 7 (seq 6)" or
    an artefact path), ``what`` (for people), ``kind`` (for programs): "unreadable" (a damaged
    line), "sequence", "edited", "chain", "found-earlier" (recorded by a run in a
    trail-problems-found entry), "unfinished-run" (the last run has no end: running, killed or
    cut), "unrecorded" (a stage output or result no entry records), "head-missing" (an anchor
    kept outside is not in the trail), "artefact-missing", "artefact-changed"."""

    where: str
    what: str
    kind: str

    def __str__(self) -> str:
        return f"{self.where}: {self.what}"


def _artefacts(entry: dict[str, Any]) -> dict[str, str]:
    """Artefact path -> sha256 recorded by this entry."""
    return dict(entry.get("artefacts") or {})


def _unrecorded(run_dir: Path, expected: dict[str, Any]) -> list[AuditProblem]:
    """What the folder holds that no entry records: a stage folder or a published result with no
    entry naming it means the trail lost its end (cut, or emptied), or the thing was put there."""
    problems = []
    recorded_folders = {"/".join(rel.split("/")[:3]) for rel in expected if rel.startswith("stages/")}
    stages = run_dir / "stages"
    for folder in sorted(stages.glob("*/*")) if stages.is_dir() else []:
        rel = folder.relative_to(run_dir).as_posix()
        if folder.is_dir() and not folder.name.startswith(".") and rel not in recorded_folders:
            problems.append(AuditProblem(rel, "no trail entry records this stage output (the trail was cut "
                                              "short, or the folder was put there)", "unrecorded"))
    results = run_dir / "results"
    for path in sorted(results.iterdir()) if results.is_dir() else []:
        rel = path.relative_to(run_dir).as_posix()
        if not path.name.startswith(".") and rel not in expected:
            problems.append(AuditProblem(rel, "no run-finished entry records this result (the trail was cut "
                                              "short, or the file was put there)", "unrecorded"))
    return problems


def recorded(run_dir: Path, prefix: str) -> tuple[dict[str, str], int | None]:
    """What the trail last recorded for the artefacts under ``prefix`` (a folder relative to the
    run folder, e.g. ``stages/merge/<key>``): path -> sha256 from the latest entry naming any of
    them, and that entry's line; ({}, None) when no entry names them (or there is no trail)."""
    try:
        entries = read_trail(run_dir)
    except FileNotFoundError:
        return {}, None
    head = prefix.rstrip("/") + "/"
    for number in range(len(entries), 0, -1):
        named = {k: v for k, v in _artefacts(entries[number - 1]).items() if k.startswith(head)}
        if named:
            return named, number
    return {}, None


def verify_trail(run_dir: Path, *, artefacts: bool = True, heads: dict[str, str] | None = None) -> list[AuditProblem]:
    """Every break in the chain, every stage folder or result no entry records (a trail cut short
    or emptied), and (with ``artefacts``) every recorded artefact whose content no longer matches:
    the latest entry naming a path decides what it should hold. ``heads``: entry hashes kept
    outside the folder (the catalog's run-finished entry, one noted from a run's output) -> where
    they were kept; the trail must still hold each: a trail cut back together with the files its
    last entries recorded, or rewritten and re-chained, passes every other check. Empty: intact."""
    run_dir = Path(run_dir)
    problems: list[AuditProblem] = []
    prev = GENESIS
    expected: dict[str, tuple[str, int]] = {}
    entries = read_trail(run_dir)
    for number, entry in enumerate(entries, start=1):
        where = f"trail line {number}"
        if "_unreadable" in entry:
            problems.append(AuditProblem(where, f"unreadable ({entry['_unreadable']})", "unreadable"))
            prev = None
            continue
        where = f"trail line {number} (seq {entry.get('seq')}, {entry.get('kind')})"
        if entry.get("seq") != number - 1:
            problems.append(AuditProblem(where, f"sequence number {entry.get('seq')}, expected {number - 1} "
                                                "(a line was removed, inserted or moved)", "sequence"))
        if _digest(entry) != entry.get("hash"):
            problems.append(AuditProblem(where, "its content does not match its hash (the entry was edited)", "edited"))
        if prev is not None and entry.get("prev") != prev:
            problems.append(AuditProblem(where, "does not chain to the entry before it (an entry before it "
                                                "was edited, removed or reordered)", "chain"))
        prev = entry.get("hash")
        if entry.get("kind") == PROBLEMS_FOUND:  # never made whole again by later entries
            problems += [AuditProblem(where, f"a run found the trail not intact before it: {found}", "found-earlier")
                         for found in entry.get("problems") or ["(no detail)"]]
        if entry.get("kind") == "run-finished":  # results/ is published as a whole: this run's replace the last's
            expected = {rel: v for rel, v in expected.items() if not rel.startswith("results/")}
        for rel, digest in _artefacts(entry).items():
            expected[rel] = (digest, number)
    runs = [(n, e.get("kind")) for n, e in enumerate(entries, start=1)
            if e.get("kind") in ("run-started", "run-finished", "run-failed", "run-stopped")]
    if runs and runs[-1][1] == "run-started":
        problems.append(AuditProblem(f"trail line {runs[-1][0]} (run-started)", "the last run has no run-finished, "
                                     "run-failed or run-stopped entry (it is still running, it was killed, or the trail was cut)",
                                     "unfinished-run"))
    problems += _unrecorded(run_dir, expected)
    held = {e.get("hash"): n for n, e in enumerate(entries, start=1)}
    for digest, source in (heads or {}).items():
        if digest not in held:
            problems.append(AuditProblem("trail", f"holds no entry with hash {digest[:12]}…, which {source} recorded "
                                                  "(the trail was cut short, or rewritten and chained anew)",
                                         "head-missing"))
    if artefacts:
        for rel, (digest, number) in sorted(expected.items()):
            path = run_dir / rel
            try:
                actual = sha256_tree(path)
            except FileNotFoundError:
                problems.append(AuditProblem(rel, f"missing (recorded at trail line {number})", "artefact-missing"))
                continue
            if actual != digest:
                problems.append(AuditProblem(rel, f"content changed: sha256 {actual[:12]}…, the trail (line {number}) "
                                                  f"recorded {digest[:12]}…", "artefact-changed"))
    return problems
