"""The one runner every stage goes through: cache key over inputs + settings + all code the stage
runs, verified lookup, build folder, commit, provenance record and audit entry.

A stage body only reads its inputs, calls ``tasks`` and writes the files its ``Stage`` declares.
"""

from __future__ import annotations

import ast
import functools
import hashlib
import importlib
import importlib.metadata
import json
import os
import shutil
import socket
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, NoReturn

from pydantic import BaseModel

from data_catalog import audit
from data_catalog.atomic import atomic_write_text
from data_catalog.hashing import sha256_file, sha256_tree
from data_catalog.passes import PassFormatError
from data_catalog.stages import RECORD_NAME, StageStore, cache_key
from flows.stages.contracts import OutputFile, StageRef, each
from schemas.manifest import PassEntry, SampleManifest
from schemas.provenance import StageRecord
from schemas.reconstruction import ReconstructionConfig

__all__ = ["Stage", "StageContext", "StageFailed", "run_stage", "code_version", "code_modules", "pass_hash"]

_PROJECT = ("schemas", "tasks", "data_catalog", "flows", "simulator")
_STORAGE_LIBRARIES = ("zarr", "numcodecs")  # they shape every stored byte, imported or not


@dataclass(frozen=True)
class StageContext:
    """What a stage body gets: its build folder, the sample, its settings and its inputs."""

    out: Path
    sample_dir: Path
    manifest: SampleManifest
    config: ReconstructionConfig
    settings: BaseModel | None
    entry: PassEntry | None
    inputs: dict[str, StageRef | list[StageRef]]

    @property
    def names(self) -> list[str]:
        return [e.pass_id for _, e in self.manifest.passes()]


@dataclass(frozen=True)
class Stage:
    """One stage, declared once. ``name`` is its name everywhere (Prefect task, store folder,
    audit trail, catalog, report); ``per_pass`` stages run once per pass; ``needs`` are the
    stages whose outputs it reads (in the registry's order); ``settings`` the section of
    ``ReconstructionConfig`` it is configured by: its own name (``"*"``: the whole config; None:
    nothing);
    ``outputs`` the files it writes; ``body`` computes them; ``manifest_view`` the part of the
    manifest it reads (hashed into its key); ``reads_input_metrics``: it reads its inputs'
    metrics as well as their files (the report), so they are hashed into its key too (without
    their ``seconds``): two runs whose stages wrote the same files with other figures (a segment
    that kept the same points of a part declared otherwise) do not share its output."""

    name: str
    per_pass: bool
    needs: tuple[str, ...]
    settings: str | None
    outputs: tuple[OutputFile, ...]
    body_at: str  # "module:function", imported when first run (the registry imports no compute)
    manifest_view_at: str  # "module:function"
    summary: str
    surfaces_body_at: str | None = None  # the body for a sample registered on its surfaces (imported scans)
    reads_input_metrics: bool = False

    @property
    def body(self) -> Callable[[StageContext], dict[str, Any]]:
        return _resolve(self.body_at)

    def body_for(self, manifest: SampleManifest) -> Callable[[StageContext], dict[str, Any]]:
        """The body that runs for ``manifest``'s sample: the surfaces variant for imported scans
        registered on their surfaces, where the stage has one."""
        return _resolve(self.surfaces_body_at if manifest.surfaces and self.surfaces_body_at else self.body_at)

    def load(self) -> None:
        """Import the stage's bodies and manifest view now. A run does it in its main thread before
        any stage runs: CPython 3.11 compiling modules in several threads at once can fail
        ("AST constructor recursion depth mismatch"), and a run's code is the code it started with."""
        for at in (self.body_at, self.surfaces_body_at, self.manifest_view_at):
            if at:
                _resolve(at)

    @property
    def body_modules(self) -> tuple[str, ...]:
        """The modules of the stage's bodies (its code version covers them all)."""
        return tuple(dict.fromkeys(at.partition(":")[0] for at in (self.body_at, self.surfaces_body_at) if at))

    @property
    def manifest_view(self) -> Callable[[SampleManifest, PassEntry | None], Any]:
        return _resolve(self.manifest_view_at)

    def settings_of(self, config: ReconstructionConfig) -> BaseModel | None:
        if self.settings is None:
            return None
        return config if self.settings == "*" else getattr(config, self.settings)


@functools.cache
def _resolve(at: str) -> Callable:
    module, _, name = at.partition(":")
    return getattr(importlib.import_module(module), name)


class StageFailed(RuntimeError):
    """A stage's body failed. ``stage`` and ``item`` (the pass) name it; ``retryable`` says
    whether a second try may pass (an IO error), not bad input."""

    def __init__(self, stage: str, item: str | None, message: str, *, retryable: bool) -> None:
        super().__init__(message)
        self.stage, self.item, self.retryable = stage, item, retryable

    def __reduce__(self):  # Dask and Prefect pickle exceptions across processes
        return (_rebuild_failure, (self.stage, self.item, str(self), self.retryable))


def _rebuild_failure(stage, item, message, retryable) -> StageFailed:
    return StageFailed(stage, item, message, retryable=retryable)


_ROOT = Path(__file__).resolve().parents[2]  # the folder of the project's packages (_PROJECT)


def _module_source(name: str) -> tuple[str, str] | None:
    """A project module's file and source, found beside this one's packages without importing it
    (a parent package's import would run it); None for a name imported from a module."""
    base = _ROOT.joinpath(*name.split("."))
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.is_file():
            return str(path), path.read_text(encoding="utf-8")
    return None


def _code_cache(kind: str, key: str, compute: Callable[[], Any]) -> Any:
    """``compute()``'s JSON value, kept between processes under ``key`` (a hash of everything it
    depends on) in ``$WELDRECON_CACHE_DIR`` (default ``~/.cache/weldrecon``): a command reads the
    code versions' ingredients back instead of parsing the project's sources and scanning every
    installed distribution again (about 1 s a process). A missing, unreadable or unwritable
    cache only costs the computation."""
    folder = Path(os.environ.get("WELDRECON_CACHE_DIR") or Path.home() / ".cache" / "weldrecon") / "code"
    path = folder / f"{kind}-{key}.json"
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        pass
    value = compute()
    try:
        folder.mkdir(parents=True, exist_ok=True)
        atomic_write_text(path, json.dumps(value, sort_keys=True))
    except OSError:
        pass
    return value


@functools.cache  # once per module and source in a process: the stages share most of their modules
def _imported_names(module: str, source: str) -> frozenset[str]:
    """Every module a source file imports, at top level or inside functions."""
    key = hashlib.sha256(f"{module}\0{source}".encode()).hexdigest()
    return frozenset(_code_cache("imports", key, lambda: sorted(_parse_imports(module, source))))


def _parse_imports(module: str, source: str) -> set[str]:
    found: set[str] = set()
    package = module if module.endswith("__init__") else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
            found.add(base)
            found.update(f"{base}.{alias.name}" for alias in node.names)
    return found


_PARSING = threading.Lock()  # CPython 3.11's ast.parse is not safe in several threads at once


def code_modules(module: str) -> tuple[tuple[str, str], tuple[str, ...]]:
    """The project modules ``module`` runs (itself and every project module it imports,
    transitively; package ``__init__`` files only when imported by name), as (name, source
    sha256) pairs, and the third-party top-level packages they import."""
    with _PARSING:
        return _code_modules(module)


@functools.cache
def _code_modules(module: str) -> tuple[tuple[str, str], tuple[str, ...]]:
    seen: dict[str, str] = {}
    third_party: set[str] = set()
    todo = [module]
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        found = _module_source(name)
        if found is None:
            continue
        _, source = found
        seen[name] = hashlib.sha256(source.encode()).hexdigest()
        for imported in _imported_names(name, source):
            top = imported.split(".")[0]
            if top in _PROJECT:
                todo.append(imported)
            elif top and top not in sys.stdlib_module_names and top != "__future__":
                third_party.add(top)
    return tuple(sorted(seen.items())), tuple(sorted(third_party))


@functools.cache
def _owners() -> dict[str, list[str]]:
    """Top-level package -> the distributions that install it (a scan of every installed one:
    ~0.4 s, so once per process, and kept between processes for the same installed set)."""
    installed = sorted(str(getattr(d, "_path", None) or (d.metadata["Name"], d.version))  # its dist-info folder
                       for d in importlib.metadata.distributions())
    key = hashlib.sha256(json.dumps([sys.prefix, sys.version, installed]).encode()).hexdigest()
    return _code_cache("owners", key, importlib.metadata.packages_distributions)


@functools.lru_cache(maxsize=None)
def _distribution_versions(packages: tuple[str, ...]) -> tuple[tuple[str, str], ...]:
    owners = _owners()
    versions = set()
    for package in packages:
        for dist in owners.get(package, [package]):
            try:
                versions.add((dist, importlib.metadata.version(dist)))
            except importlib.metadata.PackageNotFoundError:
                continue
    return tuple(sorted(versions))


def code_version(stage: Stage) -> str:
    """Hash of all the code a stage runs: its body's module and every project module that
    imports, transitively, and the versions of the libraries they import (and Python's)."""
    found = [code_modules(module) for module in stage.body_modules]
    modules = found[0][0] if len(found) == 1 else tuple(sorted({pair for pairs, _ in found for pair in pairs}))
    third_party = tuple(sorted({name for _, names in found for name in names} | set(_STORAGE_LIBRARIES)))
    payload = {"modules": modules, "libraries": _distribution_versions(third_party),
               "python": list(sys.version_info[:2])}
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:16]


def pass_hash(sample_dir: Path, entry: PassEntry) -> str:
    """The pass file's content hash; checked against the manifest's when it carries one."""
    path = Path(sample_dir) / entry.file
    if not path.exists():
        raise PassFormatError(f"pass {entry.pass_id}: pass file {path} does not exist")
    actual = sha256_tree(path)
    if entry.content_sha256 is not None and actual != entry.content_sha256:
        raise ValueError(f"pass {entry.pass_id}: {entry.file} does not match the manifest's content_sha256 "
                         f"(file changed or truncated)")
    return actual


def _input_hashes(stage: Stage, sample_dir: Path, manifest: SampleManifest, entry: PassEntry | None,
                  inputs: dict[str, StageRef | list[StageRef]]) -> dict[str, str]:
    hashes: dict[str, str] = {}
    if stage.per_pass:
        hashes["pass"] = pass_hash(sample_dir, entry)
    view = json.dumps(stage.manifest_view(manifest, entry), sort_keys=True, default=str)
    hashes["manifest"] = hashlib.sha256(view.encode()).hexdigest()
    for need, ref in inputs.items():
        for r in each(ref):
            prefix = need if r.item is None else f"{need}/{r.item}"
            hashes.update({f"{prefix}/{name}": digest for name, digest in r.outputs.items()})
            if stage.reads_input_metrics:
                figures = {k: v for k, v in r.metrics.items() if k != "seconds"}
                hashes[f"{prefix}/metrics"] = hashlib.sha256(
                    json.dumps(figures, sort_keys=True, default=str).encode()).hexdigest()
    return hashes


def _run_ids() -> dict[str, Any]:
    """The Prefect flow run and task run this stage runs in (None outside Prefect)."""
    try:
        from prefect.runtime import flow_run, task_run

        return {"flow_run_id": str(flow_run.id) if flow_run.id else None,
                "task_run_id": str(task_run.id) if task_run.id else None, "pid": os.getpid()}
    except Exception:  # noqa: BLE001 - provenance is best effort outside a run
        return {"flow_run_id": None, "task_run_id": None, "pid": os.getpid()}


def _artefacts(store: StageStore, stage: str, key: str, outputs: dict[str, str]) -> dict[str, str]:
    folder = store.path(stage, key).relative_to(store.root)
    found = {(folder / name).as_posix(): digest for name, digest in outputs.items()}
    found[(folder / RECORD_NAME).as_posix()] = sha256_file(store.root / folder / RECORD_NAME)
    return found


def _ref(stage: str, item: str | None, key: str, store: StageStore, record: StageRecord, cached: bool) -> StageRef:
    return StageRef(stage=stage, item=item, key=key, path=str(store.path(stage, key)), outputs=dict(record.outputs),
                    cached=cached, metrics=dict(record.metrics))


def run_stage(stage: Stage, *, store: StageStore, sample_dir: Path, manifest: SampleManifest,
              config: ReconstructionConfig, inputs: dict[str, StageRef | list[StageRef]],
              entry: PassEntry | None = None) -> StageRef:
    """Run ``stage`` unless the store holds its outputs (verified by hash); either way its
    provenance goes into the run folder's audit trail. A failing body is recorded in the trail
    and raised as ``StageFailed`` naming the stage and the pass."""
    if stage.per_pass != (entry is not None):
        raise ValueError(f"stage {stage.name}: {'a pass entry is' if stage.per_pass else 'no pass entry is'} expected")
    if set(inputs) != set(stage.needs):
        raise ValueError(f"stage {stage.name} needs {sorted(stage.needs)}, got {sorted(inputs)}")
    item = entry.pass_id if entry is not None else None
    settings = stage.settings_of(config)
    parameters = settings.model_dump(mode="json") if settings is not None else {}
    ids = _run_ids()
    try:
        hashes = _input_hashes(stage, sample_dir, manifest, entry, inputs)
    except (OSError, ValueError) as exc:
        _fail(store, stage.name, item, exc, ids)
    code = code_version(stage)
    key = cache_key(stage.name if item is None else f"{stage.name}/{item}", hashes, parameters, code)
    found, problem = store.verified(stage.name, key)
    untrusted = None
    if found is not None and not store.trust_folder:  # the trail vouching for it did not verify
        untrusted, found = store.set_aside(stage.name, key, "untrusted"), None
    shared = None
    if found is None and problem is None:  # not made in this folder: made by a run elsewhere?
        try:
            found = store.fetch_shared(stage.name, key)
        except OSError:  # e.g. no space for the copy: made here instead, which says what is wrong if it fails
            found = None
        shared = None if found is None else str(store.shared)
    if problem is not None:
        audit.append(store.root, "stage-recomputed", stage=stage.name, item=item, cache_key=key,
                     reason=f"cached outputs failed their hash check: {problem}; set aside and recomputed", **ids)
    if untrusted is not None:
        audit.append(store.root, "stage-recomputed", stage=stage.name, item=item, cache_key=key,
                     cause="untrusted-folder",
                     reason=f"the folder's audit trail did not verify when the run started: its stage set aside to "
                            f"{untrusted.name} and {'copied again from the stage cache' if found else 'recomputed'}",
                     **ids)
    if found is not None:
        now = _artefacts(store, stage.name, key, found.outputs)
        # consistent with itself is not enough: a record edited together with the hashes in it
        # must also match what the trail recorded when the stage was made (a trail that did not
        # verify records nothing to hold a copy from the stage cache against)
        then, line = (audit.recorded(store.root, store.path(stage.name, key).relative_to(store.root).as_posix())
                      if store.trust_folder else ({}, None))
        changed = sorted(k for k in set(now) | set(then) if now.get(k) != then.get(k)) if then else []
        if not changed:
            audit.append(store.root, "stage", stage=stage.name, item=item, cache_key=key, cached=True,
                         record=found.model_dump(mode="json"), artefacts=now,
                         **({"from_stage_cache": shared} if shared else {}), **ids)
            return _ref(stage.name, item, key, store, found, cached=True)
        aside = store.set_aside(stage.name, key, "tampered")
        audit.append(store.root, "stage-recomputed", stage=stage.name, item=item, cache_key=key,
                     reason=f"cached outputs do not match the audit trail (line {line}): "
                            f"{', '.join(Path(c).name for c in changed)}; set aside to {aside.name} and recomputed",
                     **ids)
    build = store.build_dir(stage.name)
    started = datetime.now(UTC)
    t0 = time.perf_counter()
    context = StageContext(out=build, sample_dir=Path(sample_dir), manifest=manifest, config=config,
                           settings=settings, entry=entry, inputs=inputs)
    try:
        metrics = dict(stage.body_for(manifest)(context))
        written = sorted(p.name for p in build.iterdir())
        declared = sorted(o.name for o in stage.outputs)
        required = sorted(o.name for o in stage.outputs if not getattr(o, "optional", False))
        if not set(required) <= set(written) <= set(declared):
            raise RuntimeError(f"stage {stage.name} wrote {written}, but declares {declared} ({required} required)")
    except Exception as exc:  # noqa: BLE001 - recorded, then raised as StageFailed
        shutil.rmtree(build, ignore_errors=True)
        _fail(store, stage.name, item, exc, ids)
    metrics["seconds"] = round(time.perf_counter() - t0, 3)
    record = StageRecord(sample_id=manifest.sample_id, stage=stage.name, item=item, cache_key=key, inputs=hashes,
                         outputs={name: "" for name in written}, parameters=parameters, code_version=code,
                         host=socket.gethostname(), started=started, finished=datetime.now(UTC), metrics=metrics,
                         flow_run_id=ids["flow_run_id"])
    store.commit(build, record)
    store.share(stage.name, key)
    committed = store.lookup(stage.name, key)
    audit.append(store.root, "stage", stage=stage.name, item=item, cache_key=key, cached=False,
                 record=committed.model_dump(mode="json"),
                 artefacts=_artefacts(store, stage.name, key, committed.outputs), **ids)
    return _ref(stage.name, item, key, store, committed, cached=False)


def _fail(store: StageStore, stage: str, item: str | None, exc: BaseException, ids: dict[str, Any]) -> NoReturn:
    if isinstance(exc, StageFailed):
        raise exc
    message = str(exc) or type(exc).__name__
    if item is not None and item not in message:
        message = f"pass {item}: {message}"
    audit.append(store.root, "stage-failed", stage=stage, item=item, error=f"{type(exc).__name__}: {message}", **ids)
    raise StageFailed(stage, item, message, retryable=isinstance(exc, OSError)) from exc
