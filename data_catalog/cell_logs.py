"""A real cell's logs into a sample folder (``weldrecon import CELL.yaml OUT_SAMPLE``): per pass
a profile file (one profile per line) and the robot's pose log, described by ``CELL.yaml``
(``schemas.cell.CellDescription``; the format in ``docs/cell-logs.md``).

Each pass's flange poses are joined to its profiles by time: a profile's time (the scanner's
clock) plus ``time_offset_s`` is its time on the robot's clock, where the pose log's positions are
interpolated linearly and its rotations by SLERP. Profile files are read in blocks of
``CHUNK_PROFILES`` lines, so memory does not grow with the file. The sample folder is built beside
``OUT_SAMPLE`` and renamed when complete; the same inputs give the same bytes.

Every problem with an input is a :class:`CellLogError`: one line naming the file, the line
(1-based) and the column, what was found and what was expected.
"""

from __future__ import annotations

import gzip
import itertools
import re
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import ValidationError
from scipy.spatial.transform import Rotation, Slerp

from data_catalog.atomic import atomic_directory
from data_catalog.hashing import sha256_tree
from data_catalog.manifests import MANIFEST_NAME, write_manifest
from data_catalog.passes import INTENSITY_MAX, PassWriter
from data_catalog.paths import not_a_file_reason, path_inside
from data_catalog.pointclouds import MAX_POSE_REACH_MM
from data_catalog.textfiles import read_yaml_mapping
from schemas.cell import (CellDescription, CellPass, PoseLogFormat, ProfileFormat, orientation_columns,
                          scipy_euler_sequence)
from schemas.manifest import MANIFEST_SCHEMA_VERSION, NominalMotion, PassEntry, SampleManifest, Setup

__all__ = ["CHUNK_PROFILES", "TIME_TOLERANCE_S", "CellLogError", "PoseLog", "CellImportSummary",
           "load_cell_description", "read_pose_log", "flange_poses_at", "import_cell"]

CHUNK_PROFILES = 256
"""Profiles per block read from a profile file, and per chunk of the pass store."""
TIME_TOLERANCE_S = 1e-6
"""How far a profile may lie outside the pose log's span and still count as covered (the
microsecond a time written with six decimals may be off)."""
_QUATERNION_TOLERANCE = 1e-3
_UNITS_TO_MM = {"mm": 1.0, "m": 1000.0}
_TIME_TO_S = {"s": 1.0, "ms": 1e-3}
_GZIP_MAGIC = b"\x1f\x8b"
MAX_LINE_BYTES = 1 << 20  # a profile of 4096 points is ~150 kB of text
MAX_LINES = 10_000_000  # a pass's profiles or poses: 2.8 hours at 1 kHz
_EMPTY_FIELD = re.compile(r"(?<![^,])(?![^,])")  # where a CSV line has an empty field
_POSE_BLOCK = 4096


class CellLogError(ValueError):
    """A cell's log file or CELL.yaml that cannot be imported; one line naming the file, the line
    and column, what was found and what was expected."""


@dataclass(frozen=True)
class PoseLog:
    """A pass's pose log on the robot's clock.

    time_s : (n,) float64, s, strictly increasing, n >= 2.
    position_mm : (n, 3) float64, mm, the flange's origin in the world (robot) frame.
    rotation : n rotations (scipy), the flange frame's axes in the world frame.
    """

    time_s: np.ndarray
    position_mm: np.ndarray
    rotation: Rotation


@dataclass(frozen=True)
class CellImportSummary:
    out_dir: Path
    n_passes: int
    n_profiles: int
    n_points: int


def load_cell_description(path: str | Path) -> CellDescription:
    """The CELL.yaml at ``path``; CellLogError with one line per problem (the file, the field's
    path in the YAML, what was found and what was expected)."""
    try:
        raw = read_yaml_mapping(path, "cell description (CELL.yaml)")
    except ValueError as exc:
        raise CellLogError(str(exc)) from None
    try:
        return CellDescription.model_validate(raw)
    except ValidationError as exc:
        lines = []
        for item in exc.errors():
            where = ".".join(str(p) for p in item["loc"]) or "(top level)"
            found = "" if isinstance(item.get("input"), dict) else f" (found {item.get('input')!r})"
            lines.append(f"{path}: {where}: {item['msg'].removeprefix('Value error, ')}{found}")
        raise CellLogError("\n".join(lines)) from None


# --- text files ---------------------------------------------------------------------------------

def _check_file(path: Path, what: str) -> None:
    """Refuse a missing or empty file, a ``.gz`` that is not gzip, a gzip file or binary data
    under another name, before reading it."""
    reason = not_a_file_reason(path)
    if reason is not None:
        raise CellLogError(f"{path}: {reason}, expected {what} as a regular file")
    with open(path, "rb") as handle:
        head = handle.read(4096)
    if not head:
        raise CellLogError(f"{path}: empty file (0 bytes), expected {what}")
    gzipped = path.name.lower().endswith(".gz")
    if gzipped and not head.startswith(_GZIP_MAGIC):
        raise CellLogError(f"{path}: not a gzip file: it starts with {head[:8]!r}, expected the gzip magic bytes "
                           f"{_GZIP_MAGIC!r} (its name ends in .gz)")
    if not gzipped and head.startswith(_GZIP_MAGIC):
        raise CellLogError(f"{path}: gzip-compressed data, but its name does not end in .gz; expected {what} "
                           "as plain text (or the name ending in .gz)")
    nul = head.find(b"\0")
    if not gzipped and nul >= 0:
        raise CellLogError(f"{path}: binary data (a NUL byte at byte {nul}), expected {what} as text")


def _data_lines(path: Path, header_lines: int, what: str) -> Iterator[tuple[int, str]]:
    """(line number from 1, stripped text) of each line after the first ``header_lines`` that is
    not blank, the file decompressed if its name ends in ``.gz``."""
    _check_file(path, what)
    gzipped = path.name.lower().endswith(".gz")
    number = 0
    try:
        with (gzip.open(path, "rb") if gzipped else open(path, "rb")) as handle:
            while raw := handle.readline(MAX_LINE_BYTES + 1):
                number += 1
                if len(raw) > MAX_LINE_BYTES and not raw.endswith(b"\n"):
                    raise CellLogError(f"{path}: line {number} is longer than {MAX_LINE_BYTES:,} bytes"
                                       f"{' decompressed' if gzipped else ''}; expected {what} (one line per "
                                       "profile or pose)")
                if number > MAX_LINES:
                    raise CellLogError(f"{path}: more than {MAX_LINES:,} lines{' decompressed' if gzipped else ''}; "
                                       f"expected {what} of one pass (at 1 kHz, {MAX_LINES / 3.6e6:.1f} hours)")
                text = raw.decode("utf-8").strip()
                if number > header_lines and text:
                    yield number, text
    except UnicodeDecodeError as exc:
        raise CellLogError(f"{path}: line {number}: not UTF-8 text ({exc.object[exc.start:exc.start + 1]!r} at "
                           f"byte {exc.start + 1} of the line), expected {what}") from None
    except (OSError, EOFError, zlib.error) as exc:
        kind = "gzip-compressed text" if gzipped else "text"
        raise CellLogError(f"{path}: cannot be read as {kind} after line {number} ({exc}); expected {what}") from None


def _tokens(text: str, delimiter: str) -> list[str]:
    return [t.strip() for t in text.split(",")] if delimiter == "csv" else text.split()


def _parse_rows(path: Path, rows: list[tuple[int, str]], *, delimiter: str, n_columns: int, empty_is_nan: bool,
                column_name: Callable[[int], str], layout: str) -> np.ndarray:
    """(len(rows), n_columns) float64 of data lines; CellLogError naming the first line whose
    column count is not ``n_columns`` (``layout``: what the columns are, in words) or the first
    field that is not a number."""
    texts = [text for _, text in rows]
    if empty_is_nan:
        texts = [_EMPTY_FIELD.sub("nan", text) for text in texts]
    problem = f"{n_columns} columns expected"
    try:
        table = np.loadtxt(texts, delimiter="," if delimiter == "csv" else None, dtype=np.float64, ndmin=2,
                           comments=None)
        if table.shape[1] == n_columns:
            return table
    except ValueError as exc:
        problem = str(exc).splitlines()[0]
    for (number, _), text in zip(rows, texts):
        tokens = _tokens(text, delimiter)
        if len(tokens) != n_columns:
            raise CellLogError(f"{path}: line {number}: {len(tokens)} columns ({delimiter}-separated), expected "
                               f"{n_columns}: {layout}")
        for k, token in enumerate(tokens):
            if not _is_number(token):
                raise CellLogError(f"{path}: line {number}, column {k + 1} ({column_name(k)}): found {token[:40]!r}, "
                                   "expected a number")
    raise CellLogError(f"{path}: lines {rows[0][0]}-{rows[-1][0]}: not readable as numbers ({problem})")


def _is_number(token: str) -> bool:
    """Whether numpy's text reader takes ``token`` as a number: what Python's float takes, in
    ASCII, without the digit separator ``_``."""
    try:
        float(token)
    except ValueError:
        return False
    return token.isascii() and "_" not in token


def _field_error(path: Path, line: int, column: int, name: str, found: str, expected: str) -> CellLogError:
    return CellLogError(f"{path}: line {line}, column {column + 1} ({name}): found {found}, expected {expected}")


def _check_increasing(path: Path, lines: np.ndarray, time: np.ndarray, column: int, unit: str) -> None:
    """Strictly increasing times; CellLogError naming the first line that is not after the one before."""
    step = np.diff(time)
    if (step <= 0).any():
        k = int(np.argmax(step <= 0)) + 1
        raise _field_error(path, int(lines[k]), column, "time", f"{time[k]:.9g} {unit}",
                           f"a time after line {lines[k - 1]}'s {time[k - 1]:.9g} {unit} (strictly increasing)")


# --- pose logs ----------------------------------------------------------------------------------

def read_pose_log(path: str | Path, fmt: PoseLogFormat, *, T_flange_tcp: np.ndarray | None = None) -> PoseLog:
    """A pose log's flange poses: positions to mm, rotations by ``fmt.orientation``; a TCP pose
    log (``fmt.pose_of`` tcp) is moved to the flange, ``T_world_flange = T_world_tcp @
    inv(T_flange_tcp)`` (``T_flange_tcp`` (4, 4), mm). Times stay on the robot's clock (s)."""
    path = Path(path)
    what = f"a pose log ({', '.join(fmt.columns)}; {fmt.delimiter}-separated)"
    lines, blocks = [], []
    rows_iter = _data_lines(path, fmt.header_lines, what)
    while rows := list(itertools.islice(rows_iter, _POSE_BLOCK)):
        blocks.append(_parse_rows(path, rows, delimiter=fmt.delimiter, n_columns=len(fmt.columns), empty_is_nan=False,
                                  column_name=lambda k: fmt.columns[k], layout=f"columns {', '.join(fmt.columns)}"))
        lines.extend(number for number, _ in rows)
    if sum(len(b) for b in blocks) < 2:
        raise CellLogError(f"{path}: {sum(len(b) for b in blocks)} pose line(s), expected at least 2 ({what})")
    table, lines = np.concatenate(blocks), np.asarray(lines)
    bad = ~np.isfinite(table)
    if bad.any():
        row, col = (int(v[0]) for v in np.nonzero(bad))
        raise _field_error(path, int(lines[row]), col, fmt.columns[col], f"{table[row, col]}", "a finite number")
    column = {name: k for k, name in enumerate(fmt.columns)}
    time_s = table[:, column["time"]] * _TIME_TO_S[fmt.time_unit]
    _check_increasing(path, lines, time_s, column["time"], "s")
    position = table[:, [column[c] for c in "xyz"]] * _UNITS_TO_MM[fmt.units]
    _check_position_units(path, fmt, lines, table[:, [column[c] for c in "xyz"]])
    rotation = _rotations(path, fmt, lines, table, column)
    if T_flange_tcp is not None:
        T_tcp_flange = np.linalg.inv(np.asarray(T_flange_tcp, dtype=np.float64))
        position = position + rotation.apply(T_tcp_flange[:3, 3])
        rotation = rotation * Rotation.from_matrix(T_tcp_flange[:3, :3])
    return PoseLog(time_s=time_s, position_mm=position, rotation=rotation)


def _check_position_units(path: Path, fmt: PoseLogFormat, lines: np.ndarray, position: np.ndarray) -> None:
    """Refuse positions that are clearly in the other unit: a flange within 5 mm of the robot's
    origin for a whole pass (metres written, mm declared), or 50 m away (mm written, m declared)."""
    reach = float(np.abs(position).max())
    x, y, z = (fmt.columns.index(c) for c in "xyz")
    if fmt.units == "mm" and reach < 5.0:
        raise CellLogError(f"{path}: lines {lines[0]}-{lines[-1]}, columns {x + 1}, {y + 1}, {z + 1} (x, y, z): every "
                           f"position within {reach:.4g} of the robot's origin; expected mm as pose_format.units says "
                           "(a flange never stays within 5 mm of the base for a whole pass: are they metres?)")
    if fmt.units == "m" and reach > 50.0:
        raise CellLogError(f"{path}: lines {lines[0]}-{lines[-1]}, columns {x + 1}, {y + 1}, {z + 1} (x, y, z): "
                           f"positions up to {reach:.4g} m from the robot's origin; expected metres as "
                           "pose_format.units says (no cell is 50 m across: are they mm?)")
    scale = 1000.0 if fmt.units == "m" else 1.0
    far = np.abs(position).max(axis=1) * scale > MAX_POSE_REACH_MM
    if far.any():  # one wild line among sane ones: a typo or a corrupted log, never a pose
        k = int(np.argmax(far))
        raise CellLogError(f"{path}: line {lines[k]}, columns {x + 1}, {y + 1}, {z + 1} (x, y, z): a position "
                           f"{float(np.abs(position[k]).max()):.4g} {fmt.units} from the robot's origin; expected "
                           f"within {MAX_POSE_REACH_MM / 1000:g} m of it (no cell is larger)")


def _rotations(path: Path, fmt: PoseLogFormat, lines: np.ndarray, table: np.ndarray,
               column: dict[str, int]) -> Rotation:
    """The rotation of each pose line, read by ``fmt.orientation`` from the ``table`` columns ``column`` names."""
    names = orientation_columns(fmt.orientation)
    values = table[:, [column[c] for c in names]]
    if fmt.orientation == "quaternion":
        norm = np.linalg.norm(values, axis=1)
        off = np.abs(norm - 1.0) > _QUATERNION_TOLERANCE
        if off.any():
            row = int(np.argmax(off))
            raise CellLogError(f"{path}: line {lines[row]}, columns {', '.join(str(column[c] + 1) for c in names)} "
                               f"(qw, qx, qy, qz): found a quaternion of norm {norm[row]:.6g}, expected a unit "
                               f"quaternion (norm 1 within {_QUATERNION_TOLERANCE:g})")
        return Rotation.from_quat(values[:, [1, 2, 3, 0]] / norm[:, None])  # scipy: scalar last
    degrees = fmt.angle_unit != "rad"
    if fmt.orientation == "rotation-vector":
        return Rotation.from_rotvec(values, degrees=degrees)
    return Rotation.from_euler(scipy_euler_sequence(fmt.orientation), values, degrees=degrees)


def flange_poses_at(log: PoseLog, time_s: np.ndarray) -> np.ndarray:
    """T_world_flange (n, 4, 4) float64, mm, at the robot-clock times ``time_s`` (n,) s inside
    the log's span: positions interpolated linearly, rotations by SLERP."""
    t = np.clip(np.asarray(time_s, dtype=np.float64), log.time_s[0], log.time_s[-1])
    T = np.zeros((len(t), 4, 4))
    T[:, :3, :3] = Slerp(log.time_s, log.rotation)(t).as_matrix()
    T[:, :3, 3] = np.column_stack([np.interp(t, log.time_s, log.position_mm[:, k]) for k in range(3)])
    T[:, 3, 3] = 1.0
    return T


# --- profile files ------------------------------------------------------------------------------

class _ProfileFile:
    """One pass's profile file: its columns' names and meaning, its times, its blocks of profiles."""

    def __init__(self, path: Path, fmt: ProfileFormat, points: int) -> None:
        self.path, self.fmt, self.points = path, fmt, points
        if fmt.layout == "xzi":
            self.n_columns = 1 + 3 * points
            self.layout = f"the time, then X, Z, intensity for each of the scanner's {points} points"
        else:
            self.n_columns = 1 + points * (2 if fmt.intensities else 1)
            then = f" and {points} intensities" if fmt.intensities else ""
            self.layout = f"the time, then {points} Z values{then}"
        self.what = f"a profile file ({fmt.layout}: {self.layout}; {fmt.delimiter}-separated)"

    def column_name(self, k: int) -> str:
        if k == 0:
            return "time"
        if self.fmt.layout == "xzi":
            return f"{('X', 'Z', 'intensity')[(k - 1) % 3]} of point {(k - 1) // 3 + 1}"
        return f"Z of point {k}" if k <= self.points else f"intensity of point {k - self.points}"

    def rows(self) -> Iterator[tuple[int, str]]:
        return _data_lines(self.path, self.fmt.header_lines, self.what)

    def times(self) -> tuple[np.ndarray, np.ndarray]:
        """(line numbers, times in s on the scanner's clock) of every profile, checked strictly increasing."""
        lines, times = [], []
        for number, text in self.rows():
            token = text.split("," if self.fmt.delimiter == "csv" else None, 1)[0].strip()
            if not _is_number(token):
                raise _field_error(self.path, number, 0, "time", repr(token[:40]), "a number")
            value = float(token)
            if not np.isfinite(value):
                raise _field_error(self.path, number, 0, "time", repr(token[:40]), "a finite number")
            lines.append(number)
            times.append(value)
        if len(times) < 2:
            raise CellLogError(f"{self.path}: {len(times)} profile line(s), expected at least 2: {self.what}")
        lines_arr, time_s = np.asarray(lines), np.asarray(times) * _TIME_TO_S[self.fmt.time_unit]
        _check_increasing(self.path, lines_arr, time_s, 0, "s")
        return lines_arr, time_s

    def blocks(self, z_range_mm: tuple[float, float]) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """(x_mm, z_mm, intensity) of each block of CHUNK_PROFILES profiles: (rows, points) float64
        mm in the sensor frame S, NaN where there is no return; uint16 0..1023, 0 there."""
        fmt, rows_iter = self.fmt, self.rows()
        first = True
        while rows := list(itertools.islice(rows_iter, CHUNK_PROFILES)):
            table = _parse_rows(self.path, rows, delimiter=fmt.delimiter, n_columns=self.n_columns,
                                empty_is_nan=fmt.no_return == "empty", column_name=self.column_name, layout=self.layout)
            lines = np.array([number for number, _ in rows])
            n, scale = self.points, _UNITS_TO_MM[fmt.units]
            if fmt.layout == "xzi":
                x, z, intensity = table[:, 1::3], table[:, 2::3], table[:, 3::3]
                fields = {"x": (x, 1 + 3 * np.arange(n)), "z": (z, 2 + 3 * np.arange(n))}
                i_columns = 3 + 3 * np.arange(n)
            else:
                z = table[:, 1:1 + n]
                intensity = table[:, 1 + n:] if fmt.intensities else np.zeros_like(z)
                fields, i_columns = {"z": (z, 1 + np.arange(n))}, 1 + n + np.arange(n)
            returned = self._returns(lines, fields)
            if first:
                self._check_units(lines, z[returned], z_range_mm)
                first = False
            if fmt.layout == "xzi":
                x_mm = x * scale
            else:
                spacing = fmt.x_grid.spacing_mm
                x0 = fmt.x_grid.x0_mm if fmt.x_grid.x0_mm is not None else -(n - 1) / 2 * spacing
                x_mm = np.broadcast_to(x0 + spacing * np.arange(n), z.shape)
            yield (np.where(returned, x_mm, np.nan), np.where(returned, z * scale, np.nan),
                   self._intensity(lines, intensity, returned, i_columns))

    def _returns(self, lines: np.ndarray, fields: dict[str, tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
        """Where a point was returned: none of its ``fields`` (name -> (values as written, their
        file columns)) is the no-return marker. Refuses inf, and NaN where NaN is not the marker."""
        marker = self.fmt.no_return
        missing = np.zeros(next(iter(fields.values()))[0].shape, dtype=bool)
        for values, columns in fields.values():
            bad = np.isinf(values) if marker in ("nan", "empty") else ~np.isfinite(values)
            if bad.any():
                row, k = (int(v[0]) for v in np.nonzero(bad))
                raise _field_error(self.path, int(lines[row]), int(columns[k]), self.column_name(int(columns[k])),
                                   f"{values[row, k]}", f"a finite number or the no-return marker {marker!r}")
            missing |= np.isnan(values) if marker in ("nan", "empty") else values == marker
        return ~missing

    def _intensity(self, lines: np.ndarray, values: np.ndarray, returned: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """The returns' intensities rescaled from the file's bits to 10 (uint16 0..1023; 0 where no return);
        an intensity that is not an integer in 0..2^bits-1 is refused."""
        top = 2 ** self.fmt.intensity_bits - 1
        bad = returned & ~(np.isfinite(values) & (values == np.round(values)) & (values >= 0) & (values <= top))
        if bad.any():
            row, k = (int(v[0]) for v in np.nonzero(bad))
            raise _field_error(self.path, int(lines[row]), int(cols[k]), self.column_name(int(cols[k])),
                               f"{values[row, k]:g}", f"an integer 0..{top} (intensity_bits {self.fmt.intensity_bits})")
        scaled = np.rint(np.where(returned, values, 0.0) * (INTENSITY_MAX / top))
        return scaled.astype(np.uint16)

    def _check_units(self, lines: np.ndarray, z_file: np.ndarray, z_range_mm: tuple[float, float]) -> None:
        """Refuse a first block whose returns lie, as declared, 10 times outside the scanner's range
        and inside it read in the other unit (metres declared mm, or mm declared metres)."""
        if z_file.size == 0:
            return
        near, far = z_range_mm
        declared, other = self.fmt.units, "m" if self.fmt.units == "mm" else "mm"
        median = float(np.median(z_file))
        as_declared, as_other = median * _UNITS_TO_MM[declared], median * _UNITS_TO_MM[other]
        if not (near / 10 <= as_declared <= far * 10) and near <= as_other <= far:
            raise CellLogError(f"{self.path}: lines {lines[0]}-{lines[-1]} (Z): the returns' median Z is {median:g}, "
                               f"{as_declared:g} mm read as {declared}, outside the scanner's range {near:g}..{far:g} mm; "
                               f"read as {other} it would be {as_other:g} mm, inside: expected Z in "
                               f"{declared} as profile_format.units says (are they {other}?)")


# --- the import ---------------------------------------------------------------------------------

def import_cell(cell_yaml: str | Path, out_sample: str | Path) -> CellImportSummary:
    """Import the cell logs described by ``cell_yaml`` into the new sample folder ``out_sample``
    (manifest.json and one pass store per pass, with the flange pose of every profile). The
    folder appears only when complete; on any error nothing is left behind."""
    cell_yaml, out = Path(cell_yaml), Path(out_sample)
    if out.exists():
        raise CellLogError(f"{out}: already exists; expected a new folder for the sample (nothing was written)")
    cell = load_cell_description(cell_yaml)
    root = cell_yaml.parent
    for s, setup in enumerate(cell.setups):  # every named file, before any work: inside the folder, regular
        for p, cp in enumerate(setup.passes):
            for name, field, kind in ((cp.profiles, "profiles", "profile file"), (cp.poses, "poses", "pose log")):
                path_inside(root, name, where=f"{cell_yaml}: setups.{s}.passes.{p}.{field}",
                            what=f"the {kind} of pass {cp.pass_id}", error=CellLogError)
    setups, n_profiles = [], 0
    with atomic_directory(out) as tmp:
        (tmp / "passes").mkdir()
        for setup in cell.setups:
            entries = [_import_pass(cell, root, cp, tmp) for cp in setup.passes]
            n_profiles += sum(e.n_profiles for e in entries)
            setups.append(Setup(name=setup.name, description=setup.description, passes=entries,
                                T_world_specimen_nominal=setup.T_world_specimen_nominal,
                                placement_tolerance_mm=setup.placement_tolerance_mm))
        manifest = SampleManifest(schema_version=MANIFEST_SCHEMA_VERSION, units="mm", sample_id=cell.sample_id,
                                  created=cell.created, material=cell.material, specimen=cell.specimen, weld=cell.weld,
                                  sticker_diameter_mm=cell.sticker_diameter_mm, scanner=cell.scanner, setups=setups)
        write_manifest(tmp / MANIFEST_NAME, manifest)
    n_passes = sum(len(s.passes) for s in setups)
    return CellImportSummary(out_dir=out, n_passes=n_passes, n_profiles=n_profiles,
                             n_points=n_profiles * cell.scanner.points_per_profile)


def _import_pass(cell: CellDescription, root: Path, cp: CellPass, sample: Path) -> PassEntry:
    """One pass: its pose log read, its profiles' times joined to it, its store written block by block."""
    poses_path, profiles = root / cp.poses, _ProfileFile(root / cp.profiles, cell.profile_format,
                                                         cell.scanner.points_per_profile)
    log = read_pose_log(poses_path, cell.pose_format, T_flange_tcp=cell.T_flange_tcp)
    lines, t_scanner = profiles.times()
    t_robot = t_scanner + cell.time_offset_s
    outside = (t_robot < log.time_s[0] - TIME_TOLERANCE_S) | (t_robot > log.time_s[-1] + TIME_TOLERANCE_S)
    if outside.any():
        k = int(np.argmax(outside))
        raise CellLogError(f"{profiles.path}: line {lines[k]}, column 1 (time): the profile at {t_scanner[k]:.6f} s "
                           f"({t_robot[k]:.6f} s on the robot's clock with time_offset_s {cell.time_offset_s:g}) is "
                           f"outside the pose log's span {log.time_s[0]:.6f}..{log.time_s[-1]:.6f} s ({poses_path}); "
                           "expected poses covering every profile")
    T_world_flange = flange_poses_at(log, t_robot)
    timestamp_s = t_scanner - t_scanner[0]
    store = sample / "passes" / f"{cp.pass_id}.zarr"
    writer = PassWriter(store, pass_id=cp.pass_id, n_profiles=len(lines), n_columns=cell.scanner.points_per_profile,
                        chunk_profiles=CHUNK_PROFILES, with_poses=True)
    start, returns = 0, 0
    for x_mm, z_mm, intensity in profiles.blocks(cell.scanner.z_range_mm):
        stop = start + len(x_mm)
        returns += int(np.count_nonzero(np.isfinite(z_mm)))
        writer.write(start, x_mm=x_mm, z_mm=z_mm, intensity=intensity, timestamp_s=timestamp_s[start:stop],
                     T_world_flange=T_world_flange[start:stop])
        start = stop
    writer.close()
    if returns == 0:
        raise CellLogError(f"{profiles.path}: pass {cp.pass_id}: every point of its {len(lines)} profiles is a no-return "
                           f"(profile_format.no_return {cell.profile_format.no_return!r}); expected a pass that saw "
                           "the part")
    try:
        return PassEntry(pass_id=cp.pass_id, file=f"passes/{cp.pass_id}.zarr", direction=cp.direction,
                         n_profiles=len(lines), duration_s=float(timestamp_s[-1]),
                         nominal_motion=_nominal_motion(T_world_flange, timestamp_s, poses_path),
                         has_profile_poses=True, content_sha256=sha256_tree(store))
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
        raise CellLogError(f"{poses_path}: pass {cp.pass_id}'s sweep, from its poses and times, is not a scan's: "
                           f"{problems}") from None


def _nominal_motion(T_world_flange: np.ndarray, timestamp_s: np.ndarray, poses_path: Path) -> NominalMotion:
    """The straight sweep that fits the logged flange poses (n, 4, 4), mm, at ``timestamp_s`` (n,)
    s: the first profile's pose, the unit direction of the positions' least-squares line (first to
    last), their extent along it over the scan time (speed) and the profile rate."""
    position = T_world_flange[:, :3, 3]
    centred = position - position.mean(axis=0)
    direction = np.linalg.svd(centred, full_matrices=False)[2][0]
    if direction @ (position[-1] - position[0]) < 0:
        direction = -direction
    along = centred @ direction
    length = float(along.max() - along.min())
    if length < 1e-3:
        raise CellLogError(f"{poses_path}: the flange moves {length:.3g} mm over the pass's profiles; expected a "
                           "linear sweep")
    duration = float(timestamp_s[-1] - timestamp_s[0])
    start = T_world_flange[0].copy()
    start[3] = (0.0, 0.0, 0.0, 1.0)
    return NominalMotion(T_world_flange_start=start.tolist(), direction_world=tuple(float(v) for v in direction),
                         speed_mm_s=length / duration, profile_rate_hz=(len(timestamp_s) - 1) / duration,
                         length_mm=length)
