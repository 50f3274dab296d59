"""The scan format: one zarr v3 group per imported scan (a point cloud of any scanner), the pass
store of a sample registered on its surfaces (``registration: surfaces``).

Layout of ``<scan>.zarr`` (attributes in the group's ``zarr.json``)::

    attrs: format="weldrecon-scan", format_version=1, pass_id, units="mm", n_points,
           source (the file it was imported from), complete=true (set last)
    points_mm    (n_points, 3) float32  the scan's points in its own frame, mm, all finite
    T_world_pass (4, 4)        float64  the scan's pose (scan frame -> world), mm; only where one
                                        was given (a .conf, an E57 pose)

Chunks hold ``chunk_points`` whole points; every chunk is written, so a missing chunk file
means a truncated scan.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zarr

from data_catalog.passes import PassFormatError, check_complete, create_chunked_array

__all__ = ["SCAN_FORMAT", "SCAN_FORMAT_VERSION", "ScanData", "write_scan", "read_scan"]

SCAN_FORMAT = "weldrecon-scan"
SCAN_FORMAT_VERSION = 1
_CHUNK_POINTS = 1 << 18


@dataclass(frozen=True)
class ScanData:
    """A scan store's content: ``points_mm`` (n, 3) float64, mm, the scan's own frame;
    ``T_world_pass`` (4, 4) float64 its pose, or None."""

    pass_id: str
    points_mm: np.ndarray
    T_world_pass: np.ndarray | None


def write_scan(path: Path, *, pass_id: str, points_mm: np.ndarray, T_world_pass: np.ndarray | None,
               source: str = "", chunk_points: int = _CHUNK_POINTS) -> None:
    """Write a new scan store at ``path`` (must not exist). ``points_mm`` (n >= 1, 3) finite, mm,
    in the scan's frame; ``T_world_pass`` (4, 4) finite or None."""
    points = np.asarray(points_mm, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0 or not np.isfinite(points).all():
        raise ValueError(f"points_mm must be (n >= 1, 3) and finite, got {points.shape}")
    if T_world_pass is not None:
        T_world_pass = np.asarray(T_world_pass, dtype=np.float64)
        if T_world_pass.shape != (4, 4) or not np.isfinite(T_world_pass).all():
            raise ValueError(f"T_world_pass must be a finite (4, 4) pose, got {T_world_pass.shape}")
    group = zarr.open_group(str(path), mode="w-")
    group.attrs.update({"format": SCAN_FORMAT, "format_version": SCAN_FORMAT_VERSION, "pass_id": pass_id,
                        "units": "mm", "n_points": int(len(points)), "source": source, "complete": False})
    array = create_chunked_array(group, "points_mm", points.shape, chunk_points, "float32", np.nan)
    array[...] = points.astype(np.float32)
    if T_world_pass is not None:
        group.create_array("T_world_pass", shape=(4, 4), dtype="float64", fill_value=np.nan)[...] = T_world_pass
    group.attrs["complete"] = True


def read_scan(path: Path, *, pass_id: str) -> ScanData:
    """Read and check a scan store; PassFormatError naming the pass and the file for any deviation
    from the format (missing, not a scan store, truncated, NaN points, a pose that is not rigid)."""
    path = Path(path)
    what = f"pass {pass_id}"
    if not (path / "zarr.json").is_file():
        raise PassFormatError(f"{what}: {path} is not a zarr v3 group (no zarr.json)" if path.exists()
                              else f"{what}: pass file {path} does not exist")
    try:
        group = zarr.open_group(str(path), mode="r")
    except Exception as exc:  # zarr raises several types for unreadable metadata
        raise PassFormatError(f"{what}: cannot open {path} as a zarr group: {exc}") from exc
    attrs = dict(group.attrs)
    if attrs.get("format") != SCAN_FORMAT or attrs.get("format_version") != SCAN_FORMAT_VERSION:
        raise PassFormatError(f"{what}: {path} has format {attrs.get('format')!r} version "
                              f"{attrs.get('format_version')!r}, expected {SCAN_FORMAT!r} {SCAN_FORMAT_VERSION}")
    if attrs.get("complete") is not True:
        raise PassFormatError(f"{what}: {path} was not completely written (attribute complete is not true)")
    if attrs.get("pass_id") != pass_id:
        raise PassFormatError(f"{what}: {path} holds scan {attrs.get('pass_id')!r}, expected {pass_id!r}")
    if "points_mm" not in group:
        raise PassFormatError(f"{what}: {path} has no array points_mm")
    array = group["points_mm"]
    check_complete(array, what=what)
    if array.ndim != 2 or array.shape[1] != 3 or array.shape[0] != attrs.get("n_points"):
        raise PassFormatError(f"{what}: {path}/points_mm has shape {array.shape}, expected ({attrs.get('n_points')}, 3)")
    points = np.asarray(array[...], dtype=np.float64)
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise PassFormatError(f"{what}: {path}/points_mm has a non-finite point at row {int(np.argmax(bad))}; "
                              "expected finite coordinates (mm)")
    T = None
    if "T_world_pass" in group:
        T = np.asarray(group["T_world_pass"][...], dtype=np.float64)
        R = T[:3, :3] if T.shape == (4, 4) else np.zeros((3, 3))
        if (T.shape != (4, 4) or not np.isfinite(T).all() or not np.allclose(R.T @ R, np.eye(3), atol=1e-6)
                or np.linalg.det(R) < 0 or not np.allclose(T[3], [0, 0, 0, 1])):
            raise PassFormatError(f"{what}: {path}/T_world_pass is not a finite rigid (4, 4) pose")
    return ScanData(pass_id=pass_id, points_mm=points, T_world_pass=T)
