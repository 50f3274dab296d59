"""The sample catalog: which samples exist, what state each is in, what it produced.

An embedded SQLite database (``<workspace>/catalog.sqlite``, WAL mode): no server, safe for the
threads and processes of one machine. Several machines sharing one catalog need a database
server instead (see docs/operations.md); the schema is plain SQL.

A sample is registered from its folder (manifest + passes). Its *fingerprint* is the sha256 of
the manifest file and of every pass file's content: a sample is due for reconstruction when it is
new, when its last run failed, or when its fingerprint differs from the one its last successful
run saw (a repaired or re-scanned pass).
"""

from __future__ import annotations

import hashlib
import json
import sqlite3
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from data_catalog.hashing import sha256_file, sha256_tree
from data_catalog.manifests import MANIFEST_NAME, check_sample_files, load_manifest

__all__ = ["CATALOG_NAME", "CatalogError", "SampleState", "SampleRecord", "Catalog", "fingerprint"]

CATALOG_NAME = "catalog.sqlite"


class CatalogError(ValueError):
    """The catalog file cannot be used (damaged, not a database, not writable); names the file."""


class SampleState:
    NEW = "new"
    RUNNING = "running"
    DONE = "done"
    FAILED = "failed"


_SCHEMA = """
CREATE TABLE IF NOT EXISTS samples (
    sample_id TEXT PRIMARY KEY,
    sample_dir TEXT NOT NULL,
    fingerprint TEXT NOT NULL,
    state TEXT NOT NULL,
    failed_stage TEXT,
    error TEXT,
    out_dir TEXT,
    done_fingerprint TEXT,
    artefacts TEXT NOT NULL DEFAULT '{}',
    flow_run_id TEXT,
    registered TEXT NOT NULL,
    updated TEXT NOT NULL,
    trail_head TEXT
)
"""
# columns added since the first schema: (name, SQL type), added to an older catalog when opened
_ADDED_COLUMNS = (("trail_head", "TEXT"),)


@dataclass(frozen=True)
class SampleRecord:
    sample_id: str
    sample_dir: str
    fingerprint: str
    state: str
    failed_stage: str | None
    error: str | None
    out_dir: str | None
    done_fingerprint: str | None
    artefacts: dict[str, str]
    flow_run_id: str | None
    registered: str
    updated: str
    trail_head: dict[str, Any] | None = None  # {"seq", "hash"}: the last finished run's run-finished entry

    @property
    def due(self) -> bool:
        """New, failed, interrupted, or changed since its last successful run."""
        return self.state != SampleState.DONE or self.fingerprint != self.done_fingerprint


def fingerprint(sample_dir: Path, sample_id: str | None = None) -> str:
    """sha256 over the manifest file and every pass file's content (in manifest order).
    ``sample_id``: the sample the folder should hold; ValueError when its manifest names another
    (the sample was renamed, or its folder reused for another specimen)."""
    sample_dir = Path(sample_dir)
    manifest = load_manifest(sample_dir)
    if sample_id is not None and manifest.sample_id != sample_id:
        raise ValueError(f"the folder now holds sample {manifest.sample_id} (its manifest), not {sample_id}: the "
                         f"sample was renamed or its folder reused; {sample_id}'s run folder and results are kept "
                         "as they are")
    digest = hashlib.sha256(sha256_file(sample_dir / MANIFEST_NAME).encode())
    for _, entry in manifest.passes():
        path = sample_dir / entry.file
        digest.update(f"{entry.pass_id}:{sha256_tree(path) if path.exists() else 'missing'}\n".encode())
    return digest.hexdigest()


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")


class Catalog:
    """The catalog in ``workspace`` (created on first use)."""

    def __init__(self, workspace: Path) -> None:
        self.workspace = Path(workspace)
        self.path = self.workspace / CATALOG_NAME
        if self.workspace.exists() and not self.workspace.is_dir():
            raise CatalogError(f"workspace {self.workspace} is a file, not a folder (--workspace)")
        self.workspace.mkdir(parents=True, exist_ok=True)
        with self._connect() as db:
            db.execute("PRAGMA journal_mode=WAL")
            db.execute(_SCHEMA)
            have = {row["name"] for row in db.execute("PRAGMA table_info(samples)")}
            for name, kind in _ADDED_COLUMNS:
                if name not in have:
                    db.execute(f"ALTER TABLE samples ADD COLUMN {name} {kind}")

    @contextmanager
    def _connect(self) -> Iterator[sqlite3.Connection]:
        """A connection; any database error becomes a CatalogError naming the catalog file."""
        try:
            db = sqlite3.connect(self.path, timeout=30, isolation_level=None)
        except sqlite3.Error as exc:
            raise CatalogError(f"catalog {self.path}: cannot be opened ({exc})") from exc
        db.row_factory = sqlite3.Row
        try:
            yield db
        except sqlite3.DatabaseError as exc:
            hint = ("; it is damaged or not a catalog: move it aside (sample and run folders are untouched) and "
                    "register the samples again" if "not a database" in str(exc) or "malformed" in str(exc) else "")
            raise CatalogError(f"catalog {self.path}: {exc}{hint}") from exc
        finally:
            db.close()

    def out_dir_for(self, sample_id: str) -> Path:
        return self.workspace / "runs" / sample_id

    # -- registration -------------------------------------------------------------------------

    def register(self, sample_dir: Path) -> SampleRecord:
        """Register (or refresh) one sample folder; its manifest and files are checked first."""
        sample_dir = Path(sample_dir).resolve()
        manifest = load_manifest(sample_dir)
        check_sample_files(sample_dir, manifest)
        digest = fingerprint(sample_dir)
        now = _now()
        with self._connect() as db:
            row = db.execute("SELECT sample_dir FROM samples WHERE sample_id = ?", (manifest.sample_id,)).fetchone()
            if row is not None and Path(row["sample_dir"]) != sample_dir:
                raise ValueError(f"sample {manifest.sample_id} is already registered from {row['sample_dir']}; "
                                 f"{sample_dir} holds another sample with the same id")
            if row is None:
                db.execute("INSERT INTO samples (sample_id, sample_dir, fingerprint, state, registered, updated) "
                           "VALUES (?, ?, ?, ?, ?, ?)",
                           (manifest.sample_id, str(sample_dir), digest, SampleState.NEW, now, now))
            else:
                db.execute("UPDATE samples SET fingerprint = ?, updated = ? WHERE sample_id = ?",
                           (digest, now, manifest.sample_id))
            # a sample registered from this folder before under another id: renamed, or the folder
            # reused for another specimen; it is never rebuilt from this folder's data
            displaced = db.execute("SELECT sample_id FROM samples WHERE sample_dir = ? AND sample_id != ?",
                                   (str(sample_dir), manifest.sample_id)).fetchall()
        for row in displaced:
            self._set(row["sample_id"], state=SampleState.FAILED, failed_stage="register",
                      error=f"cannot read the sample folder {sample_dir}: the folder now holds sample "
                            f"{manifest.sample_id} (its manifest), not {row['sample_id']}: the sample was renamed or "
                            f"its folder reused; {row['sample_id']}'s run folder and results are kept as they are")
        return self.get(manifest.sample_id)

    def scan(self, folder: Path) -> tuple[list[SampleRecord], list[str]]:
        """Register every sample folder (one holding a manifest) directly under ``folder``.
        Returns the registered samples and, per folder that could not be, why: one bad sample
        never stops the others."""
        folder = Path(folder)
        if not folder.is_dir():
            raise ValueError(f"{folder}: " + ("does not exist" if not folder.exists() else
                                              "is a file, neither a sample folder (with manifest.json) nor a "
                                              "folder of sample folders"))
        registered, refused = [], []
        for child in sorted(folder.iterdir()):
            if not (child / MANIFEST_NAME).exists():
                continue
            try:
                registered.append(self.register(child))
            except CatalogError:
                raise  # the catalog itself is broken: no sample can be registered
            except Exception as exc:  # noqa: BLE001 - named in the refusals, the others go on
                refused.append(f"{child}: {exc}" if isinstance(exc, (ValueError, OSError))
                               else f"{child}: {type(exc).__name__}: {exc}")
        return registered, refused

    # -- queries ------------------------------------------------------------------------------

    @staticmethod
    def _record(row: sqlite3.Row) -> SampleRecord:
        values = dict(row)
        values["artefacts"] = json.loads(values["artefacts"] or "{}")
        values["trail_head"] = json.loads(values["trail_head"]) if values.get("trail_head") else None
        return SampleRecord(**values)

    def get(self, sample_id: str) -> SampleRecord:
        with self._connect() as db:
            row = db.execute("SELECT * FROM samples WHERE sample_id = ?", (sample_id,)).fetchone()
        if row is None:
            raise KeyError(f"sample {sample_id!r} is not in the catalog {self.path}")
        return self._record(row)

    def list(self) -> list[SampleRecord]:
        with self._connect() as db:
            return [self._record(r) for r in db.execute("SELECT * FROM samples ORDER BY sample_id")]

    def runs_in(self, folder: Path) -> list[SampleRecord]:
        """The samples whose run folder is ``folder`` (paths compared resolved)."""
        folder = Path(folder).resolve()
        return [r for r in self.list() if r.out_dir and Path(r.out_dir).resolve() == folder]

    def due(self, fresh: Iterable[str] = (), unreadable: dict[str, str] | None = None) -> list[SampleRecord]:
        """Samples to reconstruct. Their fingerprints are refreshed from disk first, except for
        the ``fresh`` sample ids (just registered: their fingerprints are current). A sample whose
        folder cannot be read (deleted, moved, damaged) is marked failed at "register" and, when
        ``unreadable`` is given, put there with why: it is neither due nor up to date."""
        fresh = set(fresh)
        out = []
        for record in self.list():
            if record.sample_id in fresh:
                if record.due:
                    out.append(record)
                continue
            try:
                current = fingerprint(Path(record.sample_dir), record.sample_id)
            except (ValueError, OSError) as exc:
                error = f"cannot read the sample folder {record.sample_dir}: {exc}"
                self._set(record.sample_id, state=SampleState.FAILED, failed_stage="register", error=error)
                if unreadable is not None:
                    unreadable[record.sample_id] = error
                continue
            if current != record.fingerprint:
                self._set(record.sample_id, fingerprint=current)
            refreshed = self.get(record.sample_id)
            if refreshed.due:
                out.append(refreshed)
        return out

    # -- state changes ------------------------------------------------------------------------

    def _set(self, sample_id: str, **fields: Any) -> None:
        fields["updated"] = _now()
        for name in ("artefacts", "trail_head"):
            if name in fields and fields[name] is not None:
                fields[name] = json.dumps(fields[name], sort_keys=True)
        columns = ", ".join(f"{k} = ?" for k in fields)
        with self._connect() as db:
            db.execute(f"UPDATE samples SET {columns} WHERE sample_id = ?", (*fields.values(), sample_id))  # noqa: S608

    def mark_running(self, sample_id: str, out_dir: Path, flow_run_id: str | None = None) -> None:
        self._set(sample_id, state=SampleState.RUNNING, out_dir=str(out_dir), failed_stage=None, error=None,
                  flow_run_id=flow_run_id)

    def mark_done(self, sample_id: str, fingerprint_seen: str, artefacts: dict[str, str],
                  trail_head: dict[str, Any] | None = None) -> None:
        """Done: the fingerprint its run saw, the published artefacts' hashes and the run-finished
        entry (``trail_head``: seq, hash), the anchor that ``audit verify`` holds the trail to."""
        self._set(sample_id, state=SampleState.DONE, done_fingerprint=fingerprint_seen, artefacts=artefacts,
                  failed_stage=None, error=None, trail_head=trail_head)

    def mark_failed(self, sample_id: str, stage: str | None, error: str) -> None:
        self._set(sample_id, state=SampleState.FAILED, failed_stage=stage, error=error)
