"""What a stage hands on: a typed reference to its finished outputs, and typed descriptions of
the files in a stage's folder (a zarr group of named arrays, a JSON document, a mesh file).

Each output file is described once (``flows/stages/outputs.py``); readers go through the
description, so a file name or an array name is spelled in exactly one place and a typo is an
error, not a silently missing array.
"""

from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
import json
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Generic, TypeVar

import numpy as np
from pydantic import BaseModel, ValidationError

from data_catalog.atomic import atomic_write_text
from data_catalog.stages import ArrayWriter, load_arrays, open_array, save_arrays

__all__ = ["StageRef", "ArrayFile", "JsonFile", "DocumentError", "MeshFile", "OutputFile", "each", "zarr_array", "BLOCK_POINTS",
           "map_in_order", "block_rows"]

A = TypeVar("A")
T_in = TypeVar("T_in")
T_out = TypeVar("T_out")

# Points per block a stage reads of a pass or of a per-pass output (about 2**20): ~100 MB of working
# arrays in the heaviest per-pass stage. Results do not depend on it.
BLOCK_POINTS = 1 << 20


def map_in_order(fn: Callable[[T_in], T_out], items: Iterable[T_in], *, workers: int = 2,
                 ahead: int = 2) -> Iterator[T_out]:
    """``fn`` of each item on ``workers`` threads, the results yielded in the items' order (what
    ``fn`` makes does not depend on the thread or the timing: the same results as a plain loop),
    at most ``workers + ahead`` items in flight (a stage's memory stays a few blocks). For work
    that releases the GIL: zarr's decompression, numpy, Numba kernels compiled ``nogil``."""
    if workers <= 1:
        yield from map(fn, items)
        return
    with concurrent.futures.ThreadPoolExecutor(workers, thread_name_prefix="blocks") as pool:
        pending: collections.deque = collections.deque()
        for item in items:
            pending.append(pool.submit(fn, item))
            if len(pending) > workers + ahead - 1:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()


def block_rows(n_columns: int, *, chunk_profiles: int = 1, points: int = BLOCK_POINTS) -> int:
    """Profiles per block: about ``points`` points, a whole number of the store's chunks."""
    rows = max(1, points // max(n_columns, 1))
    return max(chunk_profiles, rows // chunk_profiles * chunk_profiles)


@dataclass(frozen=True)
class StageRef:
    """A finished stage run: where its outputs are and their sha256, never the data itself.

    ``stage`` its registry name; ``item`` the pass for per-pass stages; ``key`` the cache key;
    ``path`` its folder in the stage store; ``outputs`` file name -> sha256; ``cached`` whether
    it was reused; ``metrics`` what the stage measured (``seconds`` the time its body took)."""

    stage: str
    item: str | None
    key: str
    path: str
    outputs: dict[str, str]
    cached: bool
    metrics: dict[str, Any] = field(default_factory=dict)

    def file(self, name: str) -> Path:
        if name not in self.outputs:
            raise KeyError(f"stage {self.stage} has no output {name!r} (it has {sorted(self.outputs)})")
        return Path(self.path) / name


def each(refs: StageRef | list[StageRef]) -> list[StageRef]:
    """The refs of one stage as a list: a per-pass stage has one per pass, the others one."""
    return refs if isinstance(refs, list) else [refs]


@dataclass(frozen=True)
class ArrayFile(Generic[A]):
    """A zarr group whose arrays are the fields of the frozen dataclass ``schema``."""

    name: str
    schema: type[A]

    @property
    def arrays(self) -> tuple[str, ...]:
        return tuple(f.name for f in dataclasses.fields(self.schema))

    def write(self, out: Path, value: A) -> None:
        if not isinstance(value, self.schema):
            raise TypeError(f"{self.name}: expected a {self.schema.__name__}, got {type(value).__name__}")
        save_arrays(Path(out) / self.name, **{n: np.asarray(getattr(value, n)) for n in self.arrays})

    def writer(self, out: Path, *, chunk_rows: int) -> ArrayWriter:
        """Write the arrays piece by piece (streaming stages); every field must be written."""
        return _CheckedWriter(Path(out) / self.name, self, chunk_rows)

    def read(self, ref: StageRef) -> A:
        """Every array, loaded."""
        loaded = load_arrays(ref.file(self.name), *self.arrays)
        return self.schema(**{n: loaded[n] for n in self.arrays})

    def open(self, ref: StageRef) -> A:
        """The arrays as attributes, each loaded when first read (``CLOUD.open(ref).points``)."""
        return _LazyArrays(ref.file(self.name), self.arrays)  # type: ignore[return-value]


class _CheckedWriter(ArrayWriter):
    """An ArrayWriter that accepts only the description's array names."""

    def __init__(self, path: Path, file: "ArrayFile", chunk_rows: int) -> None:
        super().__init__(path, chunk_rows=chunk_rows)
        self._file = file

    def _check(self, name: str) -> None:
        if name not in self._file.arrays:
            raise KeyError(f"{self._file.name} has no array {name!r} (it has {self._file.arrays})")

    def create(self, name, shape, dtype) -> None:
        self._check(name)
        super().create(name, shape, dtype)

    def append(self, name, values) -> None:
        self._check(name)
        super().append(name, values)

    def close(self) -> None:
        """Check every array of the description was created."""
        missing = [n for n in self._file.arrays if n not in self._group]
        if missing:
            raise RuntimeError(f"{self._file.name}: arrays {missing} were never written")


def zarr_array(ref: StageRef, file: "ArrayFile", name: str):
    """One array of a stage's zarr output, opened (not loaded): read it by row ranges."""
    if name not in file.arrays:
        raise KeyError(f"{file.name} has no array {name!r} (it has {file.arrays})")
    return open_array(ref.file(file.name), name)


class _LazyArrays:
    def __init__(self, path: Path, arrays: tuple[str, ...]) -> None:
        self._path, self._arrays, self._loaded = path, arrays, {}

    def __getattr__(self, name: str) -> np.ndarray:
        if name.startswith("_"):
            raise AttributeError(name)
        if name not in self._arrays:
            raise AttributeError(f"{self._path.name} has no array {name!r} (it has {self._arrays})")
        if name not in self._loaded:
            self._loaded[name] = load_arrays(self._path, name)[name]
        return self._loaded[name]


D = TypeVar("D", bound=BaseModel)


class DocumentError(ValueError):
    """A stage's JSON document that does not hold to its model (a renamed or missing field)."""


@dataclass(frozen=True)
class JsonFile(Generic[D]):
    """A JSON document (sorted keys, indented) in the stage's folder, the pydantic model ``model``
    written and read: readers get the model, never a dict (a renamed field fails where the file
    is read, naming it)."""

    name: str
    model: type[D]

    def write(self, out: Path, value: D) -> None:
        if not isinstance(value, self.model):
            raise TypeError(f"{self.name}: expected a {self.model.__name__}, got {type(value).__name__}")
        atomic_write_text(Path(out) / self.name, self.dumps(value))

    def dumps(self, value: D) -> str:
        """The document's bytes: NaN and infinities as null, keys sorted."""
        return json.dumps(json.loads(value.model_dump_json(by_alias=True)), indent=1, sort_keys=True, allow_nan=False) + "\n"

    def read(self, ref: StageRef) -> D:
        return self.read_path(ref.file(self.name))

    def read_path(self, path: Path) -> D:
        try:
            return self.model.model_validate_json(Path(path).read_bytes())
        except ValidationError as exc:
            first = exc.errors()[0]
            where = ".".join(str(p) for p in first["loc"]) or "(top level)"
            raise DocumentError(f"{path}: not a valid {self.model.__name__} ({exc.error_count()} problems; first: "
                                f"{where}: {first['msg']})") from None


@dataclass(frozen=True)
class MeshFile:
    """A mesh file in the stage's folder: a surface (binary STL, PLY) or a volume (Abaqus, VTU).
    ``optional``: the stage may leave it out (and says why in its other outputs)."""

    name: str
    optional: bool = False


@dataclass(frozen=True)
class TextFile:
    """A text document (UTF-8) in the stage's folder, e.g. an HTML page."""

    name: str

    def write_text(self, out: Path, text: str) -> None:
        atomic_write_text(Path(out) / self.name, text)

    def read_text(self, ref: StageRef) -> str:
        return ref.file(self.name).read_text(encoding="utf-8")


OutputFile = ArrayFile | JsonFile | MeshFile | TextFile
