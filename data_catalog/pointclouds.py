"""Point clouds written by other scanners' software, read into millimetres: PLY (binary or ASCII,
the Stanford organized range grid included), PCD, XYZ/CSV/TXT (optionally gzipped), E57 and
LAS/LAZ. A reading layer only: nothing here registers, filters or resamples.

The format is chosen by the file's extension (case-insensitive): ``.ply``, ``.pcd``, ``.xyz``,
``.csv``, ``.txt`` (each of the last three also ``.gz``), ``.e57``, ``.las``, ``.laz``. E57 is
metres by its standard; the other formats do not say, so their ``units`` must be given.

Every problem with a file is a :class:`PointCloudFormatError`, one line naming the file (and
the line, element or field) and what was expected; a library's own message follows a colon.
"""

from __future__ import annotations

import gzip
import io
import itertools
import warnings
import zlib
from dataclasses import dataclass
from pathlib import Path

import laspy
import numpy as np
import plyfile
import pye57
import pypcd4
from pye57.utils import convert_spherical_to_cartesian

from data_catalog.paths import not_a_file_reason
from schemas.manifest import UNITS_TO_MM

MAX_POSE_REACH_MM = 50_000.0  # a scan's pose: no scanning set-up is 50 m across

__all__ = ["UNITS_TO_MM", "MAX_POSE_REACH_MM", "POINT_CLOUD_SUFFIXES", "PointCloudFormatError", "ScanCloud", "read_point_clouds",
           "read_point_cloud", "read_conf_poses"]

_ASCII = (".xyz", ".csv", ".txt")
POINT_CLOUD_SUFFIXES = (".ply", ".pcd", *_ASCII, *(s + ".gz" for s in _ASCII), ".e57", ".las", ".laz")
# what a file of each format starts with (PCD and the ASCII formats are checked by their parser)
_MAGIC = {"ply": (b"ply\n", b"ply\r\n"), "e57": (b"ASTM-E57",), "las": (b"LASF",), "laz": (b"LASF",),
          "gz": (b"\x1f\x8b",)}
_INTENSITY_NAMES = ("intensity", "scalar_intensity")


class PointCloudFormatError(ValueError):
    """A point-cloud file that cannot be read as its extension says; the message names the file."""


@dataclass(frozen=True)
class ScanCloud:
    """One scan of a point-cloud file, in millimetres, in the file's own frame.

    points_mm : (n, 3) float64, mm, n >= 1, all finite.
    intensity : (n,) float32 as the file stores it (no unit), or None.
    normals : (n, 3) float64 (unit vectors as the file stores them), or None.
    grid_shape : (rows, cols) of an organized scan (a range image), or None.
    grid_index : (n,) int64, row * cols + col of each point's grid cell (-1: a point in no cell),
        or None; present exactly when grid_shape is.
    T_world_scan : (4, 4) float64, mm, the scan's pose where the file carries one (E57), or None.
    source : the file's path; format : its format ("ply", "pcd", "xyz", "csv", "txt", "e57",
        "las", "laz"); scan_name : the scan's name (E57) or the file's stem.
    """

    points_mm: np.ndarray
    intensity: np.ndarray | None
    normals: np.ndarray | None
    grid_shape: tuple[int, int] | None
    grid_index: np.ndarray | None
    T_world_scan: np.ndarray | None
    source: str
    format: str
    scan_name: str

    def __post_init__(self) -> None:
        p = self.points_mm
        if p.ndim != 2 or p.shape[1] != 3 or p.dtype != np.float64 or len(p) == 0:
            raise ValueError(f"points_mm must be (n >= 1, 3) float64, got {p.shape} {p.dtype}")
        n = len(p)
        for name, value, shape, dtype in (("intensity", self.intensity, (n,), np.float32),
                                          ("normals", self.normals, (n, 3), np.float64),
                                          ("grid_index", self.grid_index, (n,), np.int64),
                                          ("T_world_scan", self.T_world_scan, (4, 4), np.float64)):
            if value is not None and (value.shape != shape or value.dtype != dtype):
                raise ValueError(f"{name} must be {shape} {np.dtype(dtype)}, got {value.shape} {value.dtype}")
        if (self.grid_shape is None) != (self.grid_index is None):
            raise ValueError("grid_shape and grid_index must both be given or both be None")


def read_point_clouds(path: str | Path, *, units: str | None = None) -> list[ScanCloud]:
    """Every scan in a point-cloud file (E57 may hold several; the other formats hold one).

    units : the length unit of the file's coordinates, "mm" | "cm" | "m" | "in"; required except
        for E57 (metres by its standard: None or "m"). Coordinates are converted to mm.
    Raises FileNotFoundError for a missing file, ValueError for a missing or unknown unit,
    PointCloudFormatError for a file that cannot be read as its extension says.
    """
    path = Path(path)
    fmt = _format_of(path)
    if units is not None and units not in UNITS_TO_MM:
        raise ValueError(f"{path}: units must be one of {sorted(UNITS_TO_MM)}, got {units!r}")
    if fmt == "e57" and units not in (None, "m"):
        raise ValueError(f"{path}: E57 coordinates are metres by the standard; pass units=None or 'm', not {units!r}")
    if fmt != "e57" and units is None:
        raise ValueError(f"{path}: a .{fmt} file does not say its length unit; pass units='mm', 'cm', 'm' or 'in'")
    reason = not_a_file_reason(path)
    if reason == "no such file":
        raise FileNotFoundError(f"{path}: no such file")
    if reason is not None:
        raise PointCloudFormatError(f"{path}: {reason}, expected a .{fmt} point cloud as a regular file")
    if path.stat().st_size == 0:
        raise PointCloudFormatError(f"{path}: empty file (0 bytes), expected a .{fmt} point cloud")
    gzipped = path.name.lower().endswith(".gz")
    _check_magic(path, "gz" if gzipped else fmt)
    if fmt == "e57":
        return _read_e57(path)
    scale = UNITS_TO_MM[units]
    reader = {"ply": _read_ply, "pcd": _read_pcd, "las": _read_las, "laz": _read_las}.get(fmt, _read_ascii)
    return [reader(path, fmt, scale)]


def read_point_cloud(path: str | Path, *, units: str | None = None) -> ScanCloud:
    """The one scan of a point-cloud file (see read_point_clouds); a file of several scans is refused."""
    scans = read_point_clouds(path, units=units)
    if len(scans) != 1:
        raise PointCloudFormatError(f"{path}: holds {len(scans)} scans ({', '.join(s.scan_name for s in scans)}), "
                                    "expected one; use read_point_clouds")
    return scans[0]


def _format_of(path: Path) -> str:
    return _suffix_of(path).split(".")[1]


def _suffix_of(path: Path) -> str:
    name = path.name.lower()
    for suffix in POINT_CLOUD_SUFFIXES:
        if name.endswith(suffix):
            return suffix
    raise PointCloudFormatError(f"{path}: unknown point-cloud extension, expected one of "
                                f"{', '.join(POINT_CLOUD_SUFFIXES)}")


def _check_magic(path: Path, kind: str) -> None:
    if kind not in _MAGIC:
        return
    with open(path, "rb") as f:
        head = f.read(8)
    if not any(head.startswith(m) for m in _MAGIC[kind]):
        what = "a gzip file" if kind == "gz" else f"a valid {kind.upper()} file"
        raise PointCloudFormatError(f"{path}: not {what}: it starts with {head!r}, expected {_MAGIC[kind][0]!r}")


def _library_text(exc: BaseException) -> str:
    """The first line of a library's message (some span pages), with its type when it says nothing."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    return (lines[0][:300] if lines else "") or type(exc).__name__


def _scan(path: Path, fmt: str, points: np.ndarray, scale: float, *, intensity=None, normals=None,
          grid_shape=None, grid_index=None, T_world_scan=None, scan_name=None, row_name=None) -> ScanCloud:
    """A checked ScanCloud: at least one point, finite coordinates (row_name(i) names row i)."""
    where = f" (scan {scan_name!r})" if scan_name is not None else ""
    if len(points) == 0:
        raise PointCloudFormatError(f"{path}{where}: no points, expected at least one")
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        first = int(np.argmax(bad))
        raise PointCloudFormatError(f"{path}{where}: {int(bad.sum())} point(s) with NaN or infinite coordinates, "
                                    f"the first at {row_name(first) if row_name else f'point {first} (from 0)'}; "
                                    "expected finite x, y, z")
    return ScanCloud(
        points_mm=np.ascontiguousarray(points, dtype=np.float64) * scale,
        intensity=None if intensity is None else np.asarray(intensity, dtype=np.float32),
        normals=None if normals is None else np.ascontiguousarray(normals, dtype=np.float64),
        grid_shape=grid_shape, grid_index=grid_index, T_world_scan=T_world_scan, source=str(path), format=fmt,
        scan_name=scan_name if scan_name is not None else path.name[:-len(_suffix_of(path))])


def _fields(path: Path, table, names, what: str) -> np.ndarray:
    """(n, len(names)) float64 of a structured table's fields; a missing one is named."""
    missing = [n for n in names if n not in table.dtype.names]
    if missing:
        raise PointCloudFormatError(f"{path}: {what} has no {', '.join(missing)} field(s) "
                                    f"(it has {', '.join(table.dtype.names)}), expected x, y, z")
    return np.column_stack([np.asarray(table[n], dtype=np.float64) for n in names])


def _read_ply(path: Path, fmt: str, scale: float) -> ScanCloud:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # plyfile's loadtxt warns on every empty range_grid cell
            ply = plyfile.PlyData.read(str(path))
    except Exception as exc:  # plyfile raises PlyParseError, but also ValueError/UnicodeDecodeError
        raise PointCloudFormatError(f"{path}: not a readable PLY file: {_library_text(exc)}") from exc
    _check_ply_counts(path, ply)
    elements = [e.name for e in ply.elements]
    if "vertex" not in elements:
        raise PointCloudFormatError(f"{path}: no 'vertex' element (it has {elements}), expected one")
    vertex = ply["vertex"].data
    names = vertex.dtype.names
    normals = (_fields(path, vertex, ("nx", "ny", "nz"), "element 'vertex'")
               if {"nx", "ny", "nz"} <= set(names) else None)
    intensity = next((vertex[n] for n in _INTENSITY_NAMES if n in names), None)
    grid_shape, grid_index = _ply_range_grid(path, ply, len(vertex)) if "range_grid" in elements else (None, None)
    return _scan(path, fmt, _fields(path, vertex, ("x", "y", "z"), "element 'vertex'"), scale,
                 intensity=intensity, normals=normals, grid_shape=grid_shape, grid_index=grid_index)


def _header_end(path: Path, marker: bytes) -> int:
    """The byte offset just after the header line starting with ``marker`` (b"end_header",
    b"DATA"); -1 when not within the first 1 MiB."""
    with open(path, "rb") as handle:
        head = handle.read(1 << 20)
    at = head.find(b"\n" + marker)
    if at < 0:
        return -1
    end = head.find(b"\n", at + 1)
    return -1 if end < 0 else end + 1


def _data_lines_after(path: Path, offset: int) -> int:
    """Non-blank lines from byte ``offset`` to the end (streamed)."""
    with open(path, "rb") as handle:
        handle.seek(offset)
        return sum(1 for line in handle if line.strip())


def _check_ply_counts(path: Path, ply) -> None:
    """Refuse a PLY whose header declares fewer rows than its data holds (plyfile stops at the
    declared count and drops the rest without a word; more rows than the data holds it refuses)."""
    start = _header_end(path, b"end_header")
    if start < 0:
        return
    declared = ", ".join(f"element {e.name} {e.count}" for e in ply.elements)
    if ply.text:
        rows = sum(e.count for e in ply.elements)
        found = _data_lines_after(path, start)
        if found != rows:
            raise PointCloudFormatError(f"{path}: {found:,} data lines after the header, which declares {rows:,} "
                                        f"rows ({declared}); expected the header's counts to be the file's")
        return
    size = 0
    for element in ply.elements:
        data = element.data
        for prop in element.properties:
            if isinstance(prop, plyfile.PlyListProperty):
                lengths = np.fromiter(map(len, data[prop.name]), dtype=np.int64, count=len(data))
                size += len(data) * np.dtype(prop.len_dtype).itemsize + int(lengths.sum()) * np.dtype(prop.val_dtype).itemsize
            else:
                size += len(data) * np.dtype(prop.dtype()).itemsize
    extra = path.stat().st_size - start - size
    if extra > 0:
        raise PointCloudFormatError(f"{path}: {extra:,} bytes after the data its header declares ({declared}); "
                                    "expected the header's counts to be the file's")


def _ply_range_grid(path: Path, ply, n_vertices: int) -> tuple[tuple[int, int], np.ndarray]:
    """The Stanford range grid: obj_info num_cols/num_rows, one vertex_indices list per cell, row by row."""
    info = dict(line.split(None, 1) for line in ply.obj_info if len(line.split(None, 1)) == 2)
    shape = [info.get(key, "").strip() for key in ("num_rows", "num_cols")]
    if not all(value.isdigit() for value in shape):
        raise PointCloudFormatError(f"{path}: element 'range_grid' needs 'obj_info num_rows N' and 'obj_info "
                                    f"num_cols N' in the header, found num_rows {shape[0]!r}, num_cols {shape[1]!r}")
    rows, cols = int(shape[0]), int(shape[1])
    grid = ply["range_grid"].data
    if "vertex_indices" not in grid.dtype.names:
        raise PointCloudFormatError(f"{path}: element 'range_grid' has no 'vertex_indices' list, "
                                    f"expected one per grid cell (it has {', '.join(grid.dtype.names)})")
    cells = grid["vertex_indices"]
    if len(cells) != rows * cols:
        raise PointCloudFormatError(f"{path}: element 'range_grid' has {len(cells)} cells, expected "
                                    f"num_rows x num_cols = {rows} x {cols} = {rows * cols}")
    lengths = np.fromiter(map(len, cells), dtype=np.int64, count=len(cells))
    filled = [np.asarray(c, dtype=np.int64) for c in cells[lengths > 0]]
    vertices = np.concatenate(filled) if filled else np.zeros(0, np.int64)
    owner = np.repeat(np.arange(len(cells), dtype=np.int64), lengths)
    outside = (vertices < 0) | (vertices >= n_vertices)
    if outside.any():
        k = int(np.argmax(outside))
        raise PointCloudFormatError(f"{path}: element 'range_grid' cell {owner[k]} points to vertex {vertices[k]}, "
                                    f"expected an index below the {n_vertices} vertices "
                                    f"({int(outside.sum())} such index(es))")
    grid_index = np.full(n_vertices, -1, dtype=np.int64)
    grid_index[vertices] = owner
    if np.any(np.diff(np.sort(vertices)) == 0):  # by a sort: a plain np.unique is slow here (tasks.arrays)
        raise PointCloudFormatError(f"{path}: element 'range_grid' lists a vertex in more than one cell, "
                                    "expected each vertex in at most one")
    return (rows, cols), grid_index


def _read_pcd(path: Path, fmt: str, scale: float) -> ScanCloud:
    try:
        cloud = pypcd4.PointCloud.from_path(path)
        table = cloud.pc_data
    except Exception as exc:  # pypcd4 raises pydantic's ValidationError, ValueError, UnicodeDecodeError
        raise PointCloudFormatError(f"{path}: not a readable PCD file (expected a VERSION/FIELDS/SIZE/TYPE/COUNT/"
                                    f"WIDTH/HEIGHT/POINTS/DATA header): {_library_text(exc)}") from exc
    points = _fields(path, table, ("x", "y", "z"), "FIELDS")
    _check_pcd_counts(path, cloud.metadata, len(points))
    names = table.dtype.names
    intensity = next((table[n] for n in _INTENSITY_NAMES if n in names), None)
    normals = (_fields(path, table, ("normal_x", "normal_y", "normal_z"), "FIELDS")
               if {"normal_x", "normal_y", "normal_z"} <= set(names) else None)
    height, width = cloud.metadata.height, cloud.metadata.width
    if height <= 1:
        return _scan(path, fmt, points, scale, intensity=intensity, normals=normals)
    if height * width != len(points):  # an organized cloud: NaN marks a cell without a return
        raise PointCloudFormatError(f"{path}: WIDTH x HEIGHT = {width} x {height}, expected POINTS "
                                    f"{width * height}, found {len(points)}")
    keep = np.isfinite(points).all(axis=1)
    return _scan(path, fmt, points[keep], scale,
                 intensity=None if intensity is None else intensity[keep],
                 normals=None if normals is None else normals[keep],
                 grid_shape=(int(height), int(width)), grid_index=np.flatnonzero(keep).astype(np.int64))


def _check_pcd_counts(path: Path, meta, n_read: int) -> None:
    """Refuse a PCD whose POINTS (and WIDTH x HEIGHT) disagree with the data it holds (pypcd4
    reads what is there, more or fewer, without a word)."""
    declared = int(meta.points)
    if meta.width * meta.height != declared:
        raise PointCloudFormatError(f"{path}: WIDTH x HEIGHT = {meta.width} x {meta.height} = "
                                    f"{meta.width * meta.height}, POINTS {declared}; expected them equal")
    start = _header_end(path, b"DATA")
    if meta.data == "ascii" and start >= 0:
        found = _data_lines_after(path, start)
    elif meta.data == "binary" and start >= 0:
        row = sum(s * c for s, c in zip(meta.size, meta.count))
        found = (path.stat().st_size - start) / row if row else n_read
    else:  # binary_compressed states its own sizes
        found = n_read
    if found != declared or n_read != declared:
        shown = f"{found:,.0f}" if float(found).is_integer() else f"{found:,.2f}"
        raise PointCloudFormatError(f"{path}: POINTS {declared:,} in the header, {shown} points of data; expected the "
                                    "header's count to be the file's")


def _read_las(path: Path, fmt: str, scale: float) -> ScanCloud:
    try:
        las = laspy.read(path, laz_backend=laspy.LazBackend.Lazrs)
        points = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])  # scale, offset applied
    except Exception as exc:  # laspy raises LaspyException, lazrs its own errors
        raise PointCloudFormatError(f"{path}: not a readable {fmt.upper()} file (expected a LAS header and its "
                                    f"point records): {_library_text(exc)}") from exc
    if len(points) == 0:
        raise PointCloudFormatError(f"{path}: header field point_count is 0, expected at least one point")
    return _scan(path, fmt, points, scale, intensity=np.asarray(las.intensity))


def _read_e57(path: Path) -> list[ScanCloud]:
    try:
        e57 = pye57.E57(str(path))
    except Exception as exc:  # libe57's E57Exception
        raise PointCloudFormatError(f"{path}: not a readable E57 file: {_library_text(exc)}") from exc
    try:
        if e57.scan_count == 0:
            raise PointCloudFormatError(f"{path}: no scans in /data3D, expected at least one")
        return [_read_e57_scan(path, e57, i) for i in range(e57.scan_count)]
    finally:
        e57.close()


def _read_e57_scan(path: Path, e57, index: int) -> ScanCloud:
    name = f"scan {index}"
    try:
        header = e57.get_header(index)
        name = header["name"].value() if header.node.isDefined("name") else name
        fields = header.point_fields
        data = e57.read_scan(index, intensity="intensity" in fields,
                             row_column="rowIndex" in fields and "columnIndex" in fields,
                             transform=False, ignore_missing_fields=True)
    except Exception as exc:  # libe57's E57Exception, pye57's ValueError/Exception
        raise PointCloudFormatError(f"{path}: /data3D/{index} ({name!r}): not readable, expected cartesianX/Y/Z "
                                    f"or sphericalRange/Azimuth/Elevation points: {_library_text(exc)}") from exc
    if {"cartesianX", "cartesianY", "cartesianZ"} <= set(data):
        points = np.column_stack([data["cartesianX"], data["cartesianY"], data["cartesianZ"]])
    else:  # read_scan refuses a scan with neither coordinate system, so this one is spherical
        points = convert_spherical_to_cartesian(np.column_stack(
            [data["sphericalRange"], data["sphericalAzimuth"], data["sphericalElevation"]]))
    grid_shape = grid_index = None
    if "rowIndex" in data and len(points):
        rows, cols = data["rowIndex"].astype(np.int64), data["columnIndex"].astype(np.int64)
        grid_shape = (int(rows.max()) + 1, int(cols.max()) + 1)
        grid_index = rows * grid_shape[1] + cols
    T_world_scan = None
    if header.has_pose():
        T_world_scan = np.eye(4)
        T_world_scan[:3, :3] = header.rotation_matrix
        T_world_scan[:3, 3] = np.asarray(header.translation, dtype=np.float64) * UNITS_TO_MM["m"]
    return _scan(path, "e57", points, UNITS_TO_MM["m"], intensity=data.get("intensity"), grid_shape=grid_shape,
                 grid_index=grid_index, T_world_scan=T_world_scan, scan_name=name)


def _open_text(path: Path) -> io.TextIOBase:
    if path.name.lower().endswith(".gz"):
        return gzip.open(path, "rt", encoding="utf-8")
    return open(path, encoding="utf-8")


def _data_lines(path: Path, skip: int):
    """(line number, text) of each data line after the first `skip` lines: not blank, not a comment."""
    with _open_text(path) as f:
        for number, line in enumerate(f, start=1):
            if number > skip and line.strip() and not line.lstrip().startswith("#"):
                yield number, line.strip()


MAX_TEXT_LINE_BYTES = 1 << 20  # a line of x y z [intensity] is tens of bytes
MAX_GZIP_RATIO = 100  # scanned points as text compress 3-5 times; zeros or one line repeated, a thousand
_RATIO_FROM_BYTES = 64 << 20  # ... judged once this much is decompressed


def _check_text_limits(path: Path) -> None:
    """Stream ``path`` (decompressed if .gz) once before it is parsed, refusing a line longer than
    MAX_TEXT_LINE_BYTES (a .gz of zeros is one endless line, held whole by any line reader) and a
    .gz that decompresses to more than MAX_GZIP_RATIO times its size (a decompression bomb)."""
    gzipped = path.name.lower().endswith(".gz")
    packed = path.stat().st_size
    total, run = 0, 0
    with (gzip.open(path, "rb") if gzipped else open(path, "rb")) as handle:
        while block := handle.read(1 << 20):
            total += len(block)
            pieces = block.split(b"\n")  # the first continues the line in progress, the last starts the next
            if len(pieces) == 1:
                longest = run = run + len(block)
            else:
                longest = max(run + len(pieces[0]), max(map(len, pieces[1:-1]), default=0))
                run = len(pieces[-1])
            if max(longest, run) > MAX_TEXT_LINE_BYTES:
                raise PointCloudFormatError(f"{path}: a line longer than {MAX_TEXT_LINE_BYTES:,} bytes"
                                            f"{' decompressed' if gzipped else ''}; expected lines of x y z [intensity]")
            if gzipped and total > _RATIO_FROM_BYTES and total > MAX_GZIP_RATIO * packed:
                raise PointCloudFormatError(f"{path}: decompresses to more than {MAX_GZIP_RATIO} times its "
                                            f"{packed:,} bytes (a decompression bomb, or one line repeated); "
                                            "expected scanned points, which compress 3-5 times")


def _read_ascii(path: Path, fmt: str, scale: float) -> ScanCloud:
    """x y z [intensity] per line, separated by commas or whitespace; one header line allowed."""
    skip, delimiter = 0, None
    try:
        _check_text_limits(path)
    except _TEXT_ERRORS as exc:
        raise _unreadable_text(path, exc) from exc
    try:
        head = list(itertools.islice(_data_lines(path, 0), 2))
        if head:
            number, first = head[0]
            delimiter = "," if "," in first else None
            try:  # a first line that is not numbers is a header
                np.loadtxt(io.StringIO(first), delimiter=delimiter, ndmin=2)
            except ValueError:
                skip = number
                delimiter = "," if len(head) > 1 and "," in head[1][1] else None
        with _open_text(path) as f, warnings.catch_warnings():
            warnings.simplefilter("ignore")  # loadtxt warns on a file without data; refused below
            table = np.loadtxt(f, delimiter=delimiter, skiprows=skip, comments="#", ndmin=2, dtype=np.float64)
    except _TEXT_ERRORS as exc:
        raise _unreadable_text(path, exc) from exc
    except ValueError as exc:
        raise _ascii_line_error(path, skip, delimiter, exc) from exc
    if table.shape[1] not in (3, 4) and table.size:
        line, text = next(_data_lines(path, skip))
        raise PointCloudFormatError(f"{path}: line {line}: {table.shape[1]} columns, expected 3 or 4 "
                                    f"(x y z [intensity]), got {text[:80]!r}")
    if table.size == 0:
        raise PointCloudFormatError(f"{path}: no points (no data lines), expected lines of x y z [intensity]")

    def row_name(row: int) -> str:
        for i, (line, _) in enumerate(_data_lines(path, skip)):
            if i == row:
                return f"line {line}"
        return f"point {row}"

    return _scan(path, fmt, table[:, :3], scale, intensity=table[:, 3] if table.shape[1] == 4 else None,
                 row_name=row_name)


_TEXT_ERRORS = (OSError, EOFError, zlib.error, UnicodeDecodeError)  # gzip's and the decoder's


def _unreadable_text(path: Path, exc: BaseException) -> PointCloudFormatError:
    what = "gzip-compressed text" if path.name.lower().endswith(".gz") else "UTF-8 text"
    return PointCloudFormatError(f"{path}: not readable as {what}: {_library_text(exc)}")


def _ascii_line_error(path: Path, skip: int, delimiter: str | None, exc: ValueError) -> PointCloudFormatError:
    """Name the line loadtxt stumbled on: the first whose column count differs, or that has no number.
    The whole file is read first: a damaged gzip decodes to garbage lines before its CRC fails."""
    found, columns = None, None
    try:
        for line, text in _data_lines(path, skip):
            if found is None:
                problem, columns = _line_problem(text.split(delimiter), columns)
                found = problem and f"line {line}: {problem} (x y z [intensity]), got {text[:80]!r}"
    except _TEXT_ERRORS as text_exc:
        return _unreadable_text(path, text_exc)
    return PointCloudFormatError(f"{path}: {found or 'not readable as x y z [intensity] lines: ' + _library_text(exc)}")


def _line_problem(tokens: list[str], columns: int | None) -> tuple[str | None, int]:
    """What is wrong with one data line's tokens given the column count of the lines before, if anything."""
    if columns is not None and len(tokens) != columns:
        return f"{len(tokens)} columns, expected {columns} as on the lines before", columns
    try:
        [float(t) for t in tokens]
    except ValueError:
        return "expected numbers", len(tokens)
    return None, len(tokens)


def read_conf_poses(path: str | Path, *, units: str) -> dict[str, np.ndarray]:
    """The scan poses of a Stanford/scanalyze ``.conf`` file: each ``bmesh FILE tx ty tz qx qy qz qw``
    line -> ``{FILE: T_world_scan}`` ((4, 4) float64, mm); ``camera`` and other lines are ignored.

    The rotation is the *transpose* of the unit quaternion's matrix (scalar last), the translation
    added after it: ``p_world = R(q)^T p_scan + t``. Checked against the bunny's data (the median
    distance of each scan's points to the lab's ``bun_zipper.ply``, bun000 the identity): 0.05-0.07
    mm for all ten scans read this way; 16-129 mm for nine of them with ``R(q) p + t`` (bun180,
    turned ~180 deg about y, fits either way); 16-220 mm with ``R(q)^T (p - t)`` or ``R(q) (p + t)``;
    over 20 mm for all but bun000 with the scalar first (scanalyze keeps the matrix for OpenGL,
    column-major: read row-major it is the transpose). ``units``: of the translations, as for
    read_point_cloud. PointCloudFormatError naming the line for a malformed one."""
    path = Path(path)
    if units not in UNITS_TO_MM:
        raise ValueError(f"{path}: units must be one of {sorted(UNITS_TO_MM)}, got {units!r}")
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except UnicodeDecodeError as exc:
        raise PointCloudFormatError(f"{path}: not a text .conf file: {_library_text(exc)}") from exc
    poses: dict[str, np.ndarray] = {}
    for number, line in enumerate(lines, start=1):
        fields = line.split()
        if not fields or fields[0] != "bmesh":
            continue
        try:
            values = np.array(fields[2:9], dtype=np.float64)
        except ValueError:
            values = np.zeros(0)
        norm = float(np.linalg.norm(values[3:])) if len(values) == 7 else 0.0
        if len(fields) != 9 or not np.isfinite(values).all() or abs(norm - 1.0) > 1e-3:
            raise PointCloudFormatError(f"{path}: line {number}: expected 'bmesh FILE tx ty tz qx qy qz qw' with a "
                                        f"unit quaternion, got {line.strip()[:100]!r}")
        if fields[1] in poses:
            raise PointCloudFormatError(f"{path}: line {number}: {fields[1]} has a pose already, expected one each")
        x, y, z, w = values[3:] / norm
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        T = np.eye(4)
        T[:3, :3] = R.T
        T[:3, 3] = values[:3] * UNITS_TO_MM[units]
        far = float(np.abs(T[:3, 3]).max())
        if far > MAX_POSE_REACH_MM:
            raise PointCloudFormatError(f"{path}: line {number}: {fields[1]}'s translation reaches {far:.4g} mm from the "
                                        f"origin (read in {units}); expected a pose within {MAX_POSE_REACH_MM / 1000:g} m "
                                        "of it (no scanning set-up is larger)")
        poses[fields[1]] = T
    if not poses:
        raise PointCloudFormatError(f"{path}: no 'bmesh FILE tx ty tz qx qy qz qw' line, expected one per scan")
    return poses
