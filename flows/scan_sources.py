"""What ``weldrecon measure-weld`` takes as a SCAN, read as points in one frame (mm):

- a point file (``data_catalog.pointclouds``: PLY, PCD, XYZ/CSV/TXT, E57, LAS/LAZ) in ``--units``;
- a sample folder made by ``weldrecon import-scans`` (``manifest.json``, ``registration:
  surfaces``, one scan store per scan, ``data_catalog.scans``): every scan's points, each put in
  the world frame by its pose ``T_world_pass``; one scan without a pose is taken in its own frame,
  several without poses are refused (they are in no common frame until registered: reconstruct
  the sample and measure its run folder);
- a reconstruction's run folder (``results/`` as ``flows.stages.report.publish`` writes it): the
  published mesh's vertices, ``results/<sample_id>.ply`` (the run's common frame; the merged
  points are not published, the mesh is what the run delivers).

Anything else is refused in one line naming the folder and what was expected.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from data_catalog.manifests import MANIFEST_NAME, check_sample_files, load_manifest
from data_catalog.pointclouds import read_point_cloud
from data_catalog.scans import read_scan
from flows.stages.outputs import REPORT
from flows.stages.report import RESULTS
from schemas.manifest import ScanEntry
from tasks.frames import apply

__all__ = ["ScanPoints", "read_scan_points"]


@dataclass(frozen=True)
class ScanPoints:
    """A SCAN's points: ``points_mm`` (n, 3) float64, mm, one frame; ``kind`` "file", "sample" or
    "run"; ``files`` the files they came from (a folder's, relative to it; a file: none)."""

    path: Path
    points_mm: np.ndarray
    kind: str
    files: list[str]


_EXPECTED = (f"expected a point file, a sample folder of imported scans (weldrecon import-scans: {MANIFEST_NAME}, "
             f"registration surfaces) or a reconstruction's run folder ({RESULTS}/{REPORT.name} and "
             f"{RESULTS}/<sample_id>.ply)")


def read_scan_points(path: str | Path, *, units: str) -> ScanPoints:
    """The points of SCAN ``path`` (module description); ``units``: a point file's (a folder's
    points are mm already). FileNotFoundError / ValueError naming the path and what was expected."""
    path = Path(path)
    if not path.is_dir():
        return ScanPoints(path, read_point_cloud(path, units=units).points_mm, "file", [])
    if (path / MANIFEST_NAME).is_file():
        return _sample(path)
    if (path / RESULTS).is_dir():
        return _run(path)
    raise ValueError(f"{path}: a folder with neither {MANIFEST_NAME} nor {RESULTS}/; {_EXPECTED}")


def _sample(path: Path) -> ScanPoints:
    manifest = load_manifest(path)
    entries = [entry for _, entry in manifest.passes()]
    if manifest.registration != "surfaces" or not all(isinstance(e, ScanEntry) for e in entries):
        raise ValueError(f"{path}: a sample of robot passes (registration {manifest.registration}), not of imported "
                         f"scans; reconstruct it (weldrecon reconstruct) and give its run folder; {_EXPECTED}")
    check_sample_files(path, manifest)
    scans = [read_scan(path / e.file, pass_id=e.pass_id) for e in entries]
    posed = [s.T_world_pass is not None for s in scans]
    if len(scans) > 1 and not any(posed):
        raise ValueError(f"{path}: its {len(scans)} scans have no poses, so no common frame (the registration finds "
                         "them): reconstruct the sample and give its run folder, or give one scan")
    if any(posed) and not all(posed):
        missing = [s.pass_id for s, p in zip(scans, posed) if not p]
        raise ValueError(f"{path}: scan {missing[0]} has no pose while others have theirs; expected all or none")
    points = np.concatenate([s.points_mm if s.T_world_pass is None else apply(s.T_world_pass, s.points_mm)
                             for s in scans])
    return ScanPoints(path, points, "sample", [e.file for e in entries])


def _run(path: Path) -> ScanPoints:
    results = path / RESULTS
    plys = sorted(results.glob("*.ply"))
    if not (results / REPORT.name).is_file() or len(plys) != 1:
        found = ", ".join(p.name for p in sorted(results.iterdir())) or "nothing"
        raise ValueError(f"{path}: {RESULTS}/ holds {found}; {_EXPECTED} (a run that published its results)")
    return ScanPoints(path, read_point_cloud(plys[0], units="mm").points_mm, "run", [f"{RESULTS}/{plys[0].name}"])
