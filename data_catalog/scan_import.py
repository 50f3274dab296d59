"""Import point clouds of any scanner (``weldrecon import-scans``) into a sample folder that is
registered on its surfaces (``registration: surfaces``): a manifest and one scan store per scan
(``data_catalog.scans``), each scan's points in its own frame, in mm, with its pose where one is
given (a Stanford/scanalyze ``.conf``, or the E57 file's own) or none.

Everything is read and checked before anything is written, and the folder appears only when
complete (``atomic_directory``): a refused import leaves nothing behind. Every problem is a
``ScanImportError``, one line naming the file (and the line or field) and what was expected.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from data_catalog.atomic import atomic_directory
from data_catalog.manifests import MANIFEST_NAME, write_manifest
from data_catalog.paths import not_a_file_reason
from data_catalog.pointclouds import POINT_CLOUD_SUFFIXES, UNITS_TO_MM, PointCloudFormatError, ScanCloud, read_conf_poses, read_point_clouds
from data_catalog.scans import write_scan
from schemas.manifest import MANIFEST_SCHEMA_VERSION, SampleManifest, ScanEntry, Setup, WeldDescription

__all__ = ["ScanImportError", "ScanImportSummary", "ScansRead", "read_scans", "write_scans_sample", "import_scans",
           "SMALLEST_SCAN_MM", "LARGEST_SCAN_MM"]

SMALLEST_SCAN_MM = 1.0  # a scan whose bounding box is smaller was read in too small a unit (metres as mm)
LARGEST_SCAN_MM = 1.0e6  # 1 km: larger, too large a unit (mm as metres)
_ID = re.compile(r"[^A-Za-z0-9_.-]+")


class ScanImportError(ValueError):
    """Scans that cannot be imported as given; the message names the file and what was expected."""


@dataclass(frozen=True)
class ScansRead:
    """Scans read and checked, not yet written: each scan's points (scan frame, mm), its pass id,
    its pose (``T_world_pass``, or None) and what it came from."""

    out: Path
    scans: list[ScanCloud]
    paths: list[Path]
    pass_ids: list[str]
    T_world_pass: list[np.ndarray | None]
    sample_id: str
    created: datetime
    view_direction: tuple[float, float, float]

    def points_in_weld_frame(self, max_points: int = 2_000_000) -> tuple[np.ndarray, str]:
        """The points in the frame a sample's weld lines are given in, and its name: the world
        frame of the scans' poses (every scan, posed), or without poses the first scan's own (the
        registration holds the first scan where it is). At most ``max_points``, evenly thinned."""
        if self.T_world_pass[0] is None:
            pts, frame = self.scans[0].points_mm, f"the first scan's own ({self.paths[0].name})"
        else:
            pts = np.concatenate([s.points_mm @ T[:3, :3].T + T[:3, 3] for s, T in zip(self.scans, self.T_world_pass)])
            frame = "the world frame of the scans' poses"
        step = max(1, -(-len(pts) // max_points))
        return np.asarray(pts[::step], np.float64), frame


@dataclass(frozen=True)
class ScanImportSummary:
    out_dir: Path
    n_scans: int
    n_points: int
    with_poses: bool


def _pass_id(text: str) -> str:
    cleaned = _ID.sub("-", text).strip("-._")[:64]
    return cleaned or "scan"


def _stem(path: Path) -> str:
    """The file's name without its point-cloud extension (``d.xyz.gz`` -> ``d``)."""
    name = path.name
    suffix = next((s for s in POINT_CLOUD_SUFFIXES if name.lower().endswith(s)), "")
    return name[:len(name) - len(suffix)] if suffix and len(name) > len(suffix) else path.stem


def _conf_lines(path: Path) -> dict[str, int]:
    """Each ``bmesh`` file name of a .conf -> its line number (read_conf_poses checks the lines)."""
    out = {}
    for number, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), start=1):
        fields = line.split()
        if len(fields) >= 2 and fields[0] == "bmesh":
            out.setdefault(fields[1], number)
    return out


def _read(path: Path, units: str | None) -> list[ScanCloud]:
    try:
        scans = read_point_clouds(path, units=units)
    except FileNotFoundError:
        raise ScanImportError(f"{path}: no such file, expected a point cloud to import") from None
    except PointCloudFormatError as exc:
        raise ScanImportError(str(exc)) from None
    except ValueError as exc:  # the unit: missing, unknown, or not metres for E57
        raise ScanImportError(str(exc).replace("pass units=None or 'm'", "give --units m or none")
                              .replace("pass units='mm', 'cm', 'm' or 'in'", "give --units mm, cm, m or in")) from None
    for scan in scans:
        extent = float(np.ptp(scan.points_mm, axis=0).max())
        unit = units or "m"
        if len(scan.points_mm) > 1 and extent < SMALLEST_SCAN_MM:
            raise ScanImportError(f"{path}: scan {scan.scan_name} spans {extent:.4g} mm read in {unit}: smaller than "
                                  f"{SMALLEST_SCAN_MM:g} mm, not a part a scanner measures; are the coordinates in a "
                                  f"larger unit (give --units m)?")
        if extent > LARGEST_SCAN_MM:
            raise ScanImportError(f"{path}: scan {scan.scan_name} spans {extent:.4g} mm read in {unit}: over 1 km; "
                                  f"are the coordinates in a smaller unit (give --units mm)?")
    return scans


def _view(view_direction) -> tuple[float, float, float]:
    v = np.asarray(view_direction, dtype=np.float64)
    if v.shape != (3,) or not np.isfinite(v).all() or np.linalg.norm(v) == 0:
        raise ScanImportError(f"--view-direction {view_direction!r}: expected three finite numbers x,y,z, not all 0 "
                              "(from the surface toward the scanner, in the scans' frame)")
    v = v / np.linalg.norm(v)
    return float(v[0]), float(v[1]), float(v[2])


def import_scans(files: list[str | Path], out_sample: str | Path, *, units: str | None, poses: str | Path | None = None,
                 ignore_poses: bool = False, sample_id: str | None = None, view_direction=(0.0, 0.0, 1.0),
                 weld: WeldDescription | None = None, placement_tolerance_mm: float = 0.0) -> ScanImportSummary:
    """Import ``files`` into the new sample folder ``out_sample``: ``read_scans`` then
    ``write_scans_sample`` (their arguments)."""
    return write_scans_sample(read_scans(files, out_sample, units=units, poses=poses, ignore_poses=ignore_poses,
                                         sample_id=sample_id, view_direction=view_direction),
                              weld=weld, placement_tolerance_mm=placement_tolerance_mm)


def read_scans(files: list[str | Path], out_sample: str | Path, *, units: str | None, poses: str | Path | None = None,
               ignore_poses: bool = False, sample_id: str | None = None, view_direction=(0.0, 0.0, 1.0)) -> ScansRead:
    """Read and check ``files`` (point clouds, ``data_catalog.pointclouds`` formats) for the new
    sample folder ``out_sample`` (nothing is written). ``units``: of the files' coordinates and of the .conf's translations
    (mm, cm, m, in; None only for E57, metres by its standard). ``poses``: a .conf giving every
    scan's pose by its file name (``bmesh FILE tx ty tz qx qy qz qw``); without it the E57 files'
    own poses are used when every scan has one; ``ignore_poses``: none is used (the registration
    then finds them). ``view_direction``: from the surface toward the scanner in each scan's frame
    (default +z). ``sample_id``: default the folder's name."""
    out = Path(out_sample)
    if out.exists():
        raise ScanImportError(f"{out}: already exists; expected a new folder for the sample (nothing was written)")
    if not files:
        raise ScanImportError("no scan files given; expected one or more point clouds")
    if units is not None and units not in UNITS_TO_MM:
        raise ScanImportError(f"--units {units!r}: expected one of {', '.join(UNITS_TO_MM)}")
    if poses is not None and ignore_poses:
        raise ScanImportError("--poses and --ignore-poses contradict each other; give one or neither")
    view = _view(view_direction)
    paths = [Path(f) for f in files]
    names = [p.name for p in paths]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise ScanImportError(f"{', '.join(twice)}: given twice; expected each scan file once")
    for path in paths:  # every named file, before any work
        reason = not_a_file_reason(path)
        if reason is not None:
            raise ScanImportError(f"{path}: {reason}, expected a point cloud to import (a regular file)")
    read = [(path, scan) for path in paths for scan in _read(path, units)]
    ids = [_pass_id(_stem(path) if len([1 for p, _ in read if p == path]) == 1 else f"{_stem(path)}-{scan.scan_name}")
           for path, scan in read]
    repeated = sorted({i for i in ids if ids.count(i) > 1})
    if repeated:
        raise ScanImportError(f"scans named alike ({', '.join(repeated)}): each scan's pass id comes from its file "
                              "name; rename the files so that each is unique")
    T: list[np.ndarray | None] = [None] * len(read)
    if poses is not None:
        conf = Path(poses)
        reason = not_a_file_reason(conf)
        if reason is not None:
            raise ScanImportError(f"{conf}: {reason}, expected the scans' poses (.conf) as a regular file")
        if units is None:
            raise ScanImportError(f"{conf}: the .conf does not say its length unit; give --units (that of the scans)")
        try:
            given = read_conf_poses(conf, units=units)
        except PointCloudFormatError as exc:
            raise ScanImportError(str(exc)) from None
        lines = _conf_lines(conf)
        unknown = [name for name in given if name not in names]
        if unknown:
            raise ScanImportError(f"{conf}: line {lines[unknown[0]]}: bmesh names {unknown[0]}, which is not among the "
                                  f"scans given ({', '.join(names)}); expected a pose for each scan given and no other")
        missing = [path.name for path, _ in read if path.name not in given]
        if missing:
            raise ScanImportError(f"{conf}: no 'bmesh {missing[0]} ...' line; expected a pose for every scan given "
                                  f"(missing: {', '.join(missing)})")
        T = [given[path.name] for path, _ in read]
    elif not ignore_poses:
        own = [scan.T_world_scan for _, scan in read]
        if all(t is not None for t in own):
            T = own
        elif any(t is not None for t in own):
            without = [str(path) for (path, _), t in zip(read, own) if t is None]
            raise ScanImportError(f"{without[0]}: has no pose while other scans have theirs; expected all or none "
                                  "(give --poses FILE.conf, or --ignore-poses to let the registration find them)")
    sample_id = sample_id if sample_id is not None else _pass_id(out.name)
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}", sample_id):
        raise ScanImportError(f"--sample-id {sample_id!r}: expected a letter or digit, then letters, digits, '_', '.', "
                              "'-' (up to 64 in all)")
    # the scans' date: the newest file's modification time (importing the same files twice gives the same bytes)
    created = datetime.fromtimestamp(int(max(p.stat().st_mtime for p in paths)), tz=UTC)
    return ScansRead(out=out, scans=[scan for _, scan in read], paths=[path for path, _ in read], pass_ids=ids,
                     T_world_pass=T, sample_id=sample_id, created=created, view_direction=view)


def write_scans_sample(read: ScansRead, *, weld: WeldDescription | None = None,
                       placement_tolerance_mm: float = 0.0) -> ScanImportSummary:
    """Write the sample folder of scans read by ``read_scans``. ``weld``: the weld in the scans
    (its lines in the frame ``ScansRead.points_in_weld_frame`` names): the setup then states that
    frame as the specimen's (``T_world_specimen_nominal`` the identity), the lines within
    ``placement_tolerance_mm`` of where they are, so that the reconstruction keeps its full
    resolution around them and measures the weld there."""
    out = read.out
    if out.exists():
        raise ScanImportError(f"{out}: already exists; expected a new folder for the sample (nothing was written)")
    whole = len(read.pass_ids) == len({p for p in read.paths})
    entries = []
    with atomic_directory(out) as tmp:
        (tmp / "passes").mkdir()
        for path, scan, pass_id, pose in zip(read.paths, read.scans, read.pass_ids, read.T_world_pass):
            write_scan(tmp / "passes" / f"{pass_id}.zarr", pass_id=pass_id, points_mm=scan.points_mm,
                       T_world_pass=pose, source=path.name)
            entries.append(ScanEntry(kind="scan", pass_id=pass_id, file=f"passes/{pass_id}.zarr",
                                     n_points=len(scan.points_mm), has_pose=pose is not None,
                                     view_direction=read.view_direction,
                                     source=path.name if whole else f"{path.name}: {scan.scan_name}"))
        placed = {} if weld is None else {"T_world_specimen_nominal": np.eye(4).tolist(),
                                          "placement_tolerance_mm": placement_tolerance_mm}
        manifest = SampleManifest(schema_version=MANIFEST_SCHEMA_VERSION, units="mm", sample_id=read.sample_id,
                                  created=read.created, registration="surfaces", weld=weld,
                                  setups=[Setup(name="scans", passes=entries, **placed)])
        write_manifest(tmp / MANIFEST_NAME, manifest)
    return ScanImportSummary(out_dir=out, n_scans=len(entries), n_points=sum(e.n_points for e in entries),
                             with_poses=read.T_world_pass[0] is not None)
