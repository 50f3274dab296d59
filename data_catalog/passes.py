"""The raw pass format: one zarr v3 group per pass, chunked along profiles.

Layout of ``<pass>.zarr`` (attributes in the group's ``zarr.json``)::

    attrs: format="weldrecon-pass", format_version=1, pass_id, units="mm",
           n_profiles, n_columns, intensity_bits=10, complete=true
    x_mm         (n_profiles, n_columns) float32  X along the laser line, sensor frame S; NaN = no return
    z_mm         (n_profiles, n_columns) float32  Z range along S's z axis; NaN = no return
    intensity    (n_profiles, n_columns) uint16   backscatter, 0..1023; 0 where there is no return
    timestamp_s  (n_profiles,)           float64  time of each profile since the pass started
    T_world_flange (n_profiles, 4, 4)    float64  robot flange pose per profile (optional)

Chunks hold ``chunk_profiles`` whole profiles; every chunk is written, even an empty one, so a
missing chunk file means a truncated pass.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zarr

__all__ = ["PASS_FORMAT", "PASS_FORMAT_VERSION", "PassData", "PassFormatError", "PassWriter", "PassReader",
           "read_pass", "open_pass", "pass_is_complete", "create_chunked_array", "check_complete"]

PASS_FORMAT = "weldrecon-pass"
PASS_FORMAT_VERSION = 1
INTENSITY_MAX = 1023


# per array: the dtype kinds accepted, in words, and the largest item size (bytes)
_DTYPES = {"x_mm": ("f", "float32 (mm)"), "z_mm": ("f", "float32 (mm)"),
           "intensity": ("u", "uint16 (0..1023)"), "timestamp_s": ("f", "float64 (s)"),
           "T_world_flange": ("f", "float64 (4 x 4 poses, mm)")}
_MAX_ITEMSIZE = {"x_mm": 8, "z_mm": 8, "intensity": 2, "timestamp_s": 8, "T_world_flange": 8}


class PassFormatError(ValueError):
    """A pass store is missing, truncated or not in the weldrecon pass format."""


@dataclass(frozen=True)
class PassData:
    """One pass in memory. Shapes: grids (n_profiles, n_columns); mm; sensor frame S."""

    pass_id: str
    x_mm: np.ndarray
    z_mm: np.ndarray
    intensity: np.ndarray
    timestamp_s: np.ndarray
    T_world_flange: np.ndarray | None

    @property
    def shape(self) -> tuple[int, int]:
        return self.x_mm.shape


def create_chunked_array(group: zarr.Group, name: str, shape: tuple[int, ...], chunk_rows: int,
                         dtype: str, fill_value, compressors="auto") -> zarr.Array:
    """An array chunked along its first axis only, with every chunk written even if empty
    (``compressors``: zarr's, default its own)."""
    chunks = (max(1, min(chunk_rows, shape[0])),) + tuple(shape[1:])
    return group.create_array(name, shape=shape, chunks=chunks, dtype=dtype, fill_value=fill_value,
                              compressors=compressors, config={"write_empty_chunks": True})


def check_complete(array: zarr.Array, *, what: str) -> None:
    """Raise PassFormatError when chunks of ``array`` are missing on disk."""
    if array.nchunks_initialized != array.nchunks:
        raise PassFormatError(
            f"{what}: array '{array.basename}' has {array.nchunks_initialized} of {array.nchunks} "
            "chunks on disk; the file is truncated or was not completely written"
        )


class PassWriter:
    """Writes a pass store block by block, in bounded memory."""

    def __init__(self, path: Path, *, pass_id: str, n_profiles: int, n_columns: int,
                 chunk_profiles: int, with_poses: bool) -> None:
        self.path = Path(path)
        self.n_profiles = n_profiles
        self._group = zarr.open_group(str(self.path), mode="w-")
        self._group.attrs.update({
            "format": PASS_FORMAT, "format_version": PASS_FORMAT_VERSION, "pass_id": pass_id,
            "units": "mm", "n_profiles": n_profiles, "n_columns": n_columns,
            "intensity_bits": 10, "complete": False,
        })
        grid = (n_profiles, n_columns)
        self._x = create_chunked_array(self._group, "x_mm", grid, chunk_profiles, "float32", np.nan)
        self._z = create_chunked_array(self._group, "z_mm", grid, chunk_profiles, "float32", np.nan)
        self._i = create_chunked_array(self._group, "intensity", grid, chunk_profiles, "uint16", 0)
        self._t = create_chunked_array(self._group, "timestamp_s", (n_profiles,), chunk_profiles, "float64", np.nan)
        self._pose = (create_chunked_array(self._group, "T_world_flange", (n_profiles, 4, 4), chunk_profiles,
                                           "float64", np.nan) if with_poses else None)
        self._written = 0

    def write(self, start: int, *, x_mm: np.ndarray, z_mm: np.ndarray, intensity: np.ndarray,
              timestamp_s: np.ndarray, T_world_flange: np.ndarray | None = None) -> None:
        stop = start + len(x_mm)
        if start != self._written or stop > self.n_profiles:
            raise ValueError(f"blocks must be written in order: expected start {self._written}, got {start}")
        self._x[start:stop] = x_mm.astype(np.float32)
        self._z[start:stop] = z_mm.astype(np.float32)
        self._i[start:stop] = intensity.astype(np.uint16)
        self._t[start:stop] = timestamp_s
        if self._pose is not None:
            if T_world_flange is None:
                raise ValueError("this pass stores flange poses; T_world_flange is required")
            self._pose[start:stop] = T_world_flange
        self._written = stop

    def close(self) -> None:
        if self._written != self.n_profiles:
            raise ValueError(f"{self.path}: {self._written} of {self.n_profiles} profiles written")
        self._group.attrs["complete"] = True


def _open_pass_group(path: Path, what: str) -> zarr.Group:
    path = Path(path)
    if not path.exists():
        raise PassFormatError(f"{what}: pass file {path} does not exist")
    if not (path / "zarr.json").is_file():
        raise PassFormatError(f"{what}: {path} is not a zarr v3 group (no zarr.json)")
    try:
        group = zarr.open_group(str(path), mode="r")
    except Exception as exc:  # zarr raises several types for unreadable metadata
        raise PassFormatError(f"{what}: cannot open {path} as a zarr group: {exc}") from exc
    attrs = dict(group.attrs)
    if attrs.get("format") != PASS_FORMAT:
        raise PassFormatError(f"{what}: {path} has format {attrs.get('format')!r}, expected {PASS_FORMAT!r}")
    if attrs.get("format_version") != PASS_FORMAT_VERSION:
        raise PassFormatError(f"{what}: {path} has format_version {attrs.get('format_version')!r}, "
                              f"expected {PASS_FORMAT_VERSION}")
    if attrs.get("complete") is not True:
        raise PassFormatError(f"{what}: {path} was not completely written (attribute complete is not true)")
    return group


class PassReader:
    """A pass store opened and checked once (format, shapes, completeness), read by profile
    ranges: a per-pass stage streams its pass in blocks and never holds the whole of it."""

    def __init__(self, path: Path, *, pass_id: str | None = None) -> None:
        self.path = Path(path)
        self.what = f"pass {pass_id}" if pass_id else "pass"
        group = _open_pass_group(self.path, self.what)
        attrs = dict(group.attrs)
        n, m = attrs.get("n_profiles"), attrs.get("n_columns")
        if not (isinstance(n, int) and isinstance(m, int) and n >= 1 and m >= 1):
            raise PassFormatError(f"{self.what}: {self.path} has n_profiles {n!r} and n_columns {m!r}, "
                                  "expected positive integers")
        if attrs.get("units") != "mm":
            raise PassFormatError(f"{self.what}: {self.path} has units {attrs.get('units')!r}, expected 'mm'")
        if pass_id is not None and attrs.get("pass_id") != pass_id:
            raise PassFormatError(f"{self.what}: {self.path} holds pass {attrs.get('pass_id')!r}, not {pass_id!r}")
        expected = {"x_mm": (n, m), "z_mm": (n, m), "intensity": (n, m), "timestamp_s": (n,)}
        if "T_world_flange" in group:
            expected["T_world_flange"] = (n, 4, 4)
        self._arrays: dict[str, zarr.Array] = {}
        for name, shape in expected.items():
            if name not in group:
                raise PassFormatError(f"{self.what}: {self.path} has no array '{name}'")
            array = group[name]
            if tuple(array.shape) != shape:
                raise PassFormatError(f"{self.what}: {self.path}/{name} has shape {tuple(array.shape)}, expected {shape}")
            kinds, wanted = _DTYPES[name]
            if (array.dtype.kind not in kinds or array.dtype.itemsize > _MAX_ITEMSIZE[name]
                    or (kinds == "f" and array.dtype.itemsize < 4)):  # float16: 0.1 mm steps at 300 mm
                raise PassFormatError(f"{self.what}: {self.path}/{name} has dtype {array.dtype}, expected {wanted}")
            check_complete(array, what=f"{self.what} ({self.path})")
            self._arrays[name] = array
        self.pass_id: str = attrs.get("pass_id")
        self.n_profiles, self.n_columns = n, m
        self.chunk_profiles = int(self._arrays["x_mm"].chunks[0])

    @property
    def has_poses(self) -> bool:
        return "T_world_flange" in self._arrays

    def read_array(self, name: str, profiles: list[int]) -> np.ndarray:
        """The rows ``profiles`` of one array (a few profiles, without reading a block)."""
        return np.asarray(self._arrays[name].get_orthogonal_selection((profiles,)))

    def read(self, start: int = 0, stop: int | None = None) -> PassData:
        """Profiles ``start`` to ``stop`` (exclusive; None: to the end)."""
        stop = self.n_profiles if stop is None else stop
        if not 0 <= start <= stop <= self.n_profiles:
            raise ValueError(f"{self.what}: profiles {start}:{stop} outside 0:{self.n_profiles}")
        arrays = {}
        for name, array in self._arrays.items():
            try:
                arrays[name] = np.asarray(array[start:stop])
            except MemoryError:
                raise MemoryError(f"{self.what}: profiles {start}:{stop} of {self.path}/{name} "
                                  f"({(stop - start) * int(np.prod(array.shape[1:])) * array.dtype.itemsize / 2**20:.0f} MiB) "
                                  "do not fit in the memory left") from None
            except Exception as exc:
                raise PassFormatError(f"{self.what}: {self.path}/{name} cannot be decoded ({exc}); "
                                      "the file is corrupt") from exc
        high = arrays["intensity"] > INTENSITY_MAX
        if high.any():
            row, col = (int(v[0]) for v in np.nonzero(high))
            raise PassFormatError(f"{self.what}: {self.path}/intensity is {int(arrays['intensity'][row, col])} at "
                                  f"profile {start + row}, column {col}; expected 0..{INTENSITY_MAX} (10-bit backscatter)")
        return PassData(pass_id=self.pass_id, x_mm=arrays["x_mm"], z_mm=arrays["z_mm"], intensity=arrays["intensity"],
                        timestamp_s=arrays["timestamp_s"], T_world_flange=arrays.get("T_world_flange"))


def pass_is_complete(path: Path) -> bool:
    """Whether the pass store at ``path`` says it was completely written (its writer sets the
    group attribute ``complete`` last); False while it is absent, partial or unreadable."""
    try:
        attrs = json.loads((Path(path) / "zarr.json").read_text(encoding="utf-8")).get("attributes", {})
    except (OSError, ValueError, AttributeError):
        return False
    return isinstance(attrs, dict) and attrs.get("complete") is True


def open_pass(path: Path, *, pass_id: str | None = None) -> PassReader:
    """Open a pass store for reading by profile ranges (``PassReader``); PassFormatError naming
    the pass and the file for any deviation from the format."""
    return PassReader(path, pass_id=pass_id)


def read_pass(path: Path, *, pass_id: str | None = None, profiles: slice | None = None) -> PassData:
    """Read a pass store (or a slice of its profiles), checking its format, shapes and completeness.

    Raises PassFormatError naming the pass and the file for any deviation.
    """
    reader = PassReader(path, pass_id=pass_id)
    if profiles is None:
        return reader.read()
    start, stop, step = profiles.indices(reader.n_profiles)
    if step != 1:
        raise ValueError("read_pass reads contiguous profile ranges only")
    return reader.read(start, stop)
