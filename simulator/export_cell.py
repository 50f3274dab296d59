"""A sample written as a real cell's logs (``weldrecon export-cell``): ``CELL.yaml``, one profile
file and one pose log per pass, in the formats ``weldrecon import`` reads (``docs/cell-logs.md``).

For testing the import on known data: the pose log is written at its own rate (every
``pose_every``-th profile, and the last) on a clock ``time_offset_s`` ahead of the scanner's, so
the import's time join and SLERP are exercised. Lengths are written to 0.1 um (4 decimals in mm,
7 in m), times to 1 us, quaternions and rotation vectors (rad) to 9 decimals, angles in degrees
to 7. The same sample and options give the same bytes (gzip without a time stamp).

Output folder (written beside ``out_dir``, renamed when complete)::

    CELL.yaml
    profiles/<pass_id>.csv|.txt[.gz]
    poses/<pass_id>.csv|.txt
"""

from __future__ import annotations

import contextlib
import gzip
import io
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import numpy as np
import yaml
from pydantic import ValidationError
from scipy.spatial.transform import Rotation

from data_catalog.atomic import atomic_directory
from data_catalog.cell_logs import CHUNK_PROFILES
from data_catalog.manifests import load_manifest
from data_catalog.passes import INTENSITY_MAX, open_pass
from schemas.cell import (CellDescription, CellPass, PoseLogFormat, ProfileFormat, orientation_columns,
                          scipy_euler_sequence)
from schemas.manifest import SampleManifest, WeldDescription

__all__ = ["CellExportSummary", "GRID_TOLERANCE_MM", "export_cell"]

GRID_TOLERANCE_MM = 5e-4
"""How far a return's X may be from its column's grid X for the ``z_grid`` layout (mm)."""
_LENGTH_FORMAT = {"mm": "%.4f", "m": "%.7f"}
_LENGTH_SCALE = {"mm": 1.0, "m": 1e-3}
_TIME_FORMAT = {"s": ("%.6f", 1.0), "ms": ("%.3f", 1e3)}


@dataclass(frozen=True)
class CellExportSummary:
    out_dir: Path
    n_passes: int
    n_profiles: int
    n_poses: int



def _weld(manifest: SampleManifest) -> WeldDescription:
    """The sample's weld in the current form (a schema 1.0 manifest's centre line as its lines)."""
    if isinstance(manifest.weld, WeldDescription):
        return manifest.weld
    return WeldDescription(process=manifest.weld.process, joint=manifest.weld.joint,
                           weld_lines=manifest.weld_lines(), treatment=manifest.weld.treatment)

def export_cell(sample_dir: str | Path, out_dir: str | Path, *, layout: str = "xzi", delimiter: str = "csv",
                compress: bool = False, orientation: str = "quaternion", quaternion_order: str = "wxyz",
                angle_unit: str | None = None, units: str = "mm", time_unit: str = "s", no_return: str | float = "nan",
                intensity_bits: int = 10, pose_every: int = 3, time_offset_s: float = 0.0) -> CellExportSummary:
    """Write the sample at ``sample_dir`` (every pass with its flange pose per profile) as cell
    logs into the new folder ``out_dir``. ``layout`` xzi or z_grid (z_grid needs every return's X
    on the scanner's centred grid, within GRID_TOLERANCE_MM), ``delimiter`` csv or whitespace,
    ``compress``: gzip the profile files; ``orientation`` a rotation convention of
    ``schemas.cell`` (``quaternion_order`` wxyz or xyzw; ``angle_unit`` where the convention needs
    one); ``units`` and ``time_unit`` of both files; ``no_return`` the marker of a missing
    return; ``intensity_bits`` of the written intensities; ``pose_every``: a pose for every n-th
    profile (and the last); ``time_offset_s``: the robot's clock minus the scanner's."""
    sample_dir, out_dir = Path(sample_dir), Path(out_dir)
    manifest = load_manifest(sample_dir)
    if pose_every < 1:
        raise ValueError(f"pose_every {pose_every}: expected a whole number >= 1")
    cell = _cell_description(manifest, layout=layout, delimiter=delimiter, compress=compress, orientation=orientation,
                             quaternion_order=quaternion_order, angle_unit=angle_unit, units=units,
                             time_unit=time_unit, no_return=no_return, intensity_bits=intensity_bits,
                             time_offset_s=time_offset_s)
    profiles = poses = 0
    with atomic_directory(out_dir) as tmp:
        (tmp / "profiles").mkdir()
        (tmp / "poses").mkdir()
        for setup, cell_setup in zip(manifest.setups, cell.setups):
            for entry, cp in zip(setup.passes, cell_setup.passes):
                n_profiles, n_poses = _write_pass(sample_dir, manifest, entry.file, cell, cp, tmp, compress=compress,
                                                  pose_every=pose_every)
                profiles, poses = profiles + n_profiles, poses + n_poses
        header = f"# cell logs of sample {manifest.sample_id}, written by weldrecon export-cell (docs/cell-logs.md)\n"
        body = yaml.safe_dump(cell.model_dump(mode="json", exclude_none=True), sort_keys=False, default_flow_style=None)
        (tmp / "CELL.yaml").write_text(header + body, encoding="utf-8")
    return CellExportSummary(out_dir=out_dir, n_passes=len(manifest.passes()), n_profiles=profiles, n_poses=poses)


def _cell_description(manifest: SampleManifest, *, layout: str, delimiter: str, compress: bool, orientation: str,
                      quaternion_order: str, angle_unit: str | None, units: str, time_unit: str,
                      no_return: str | float, intensity_bits: int, time_offset_s: float) -> CellDescription:
    """The CELL.yaml of the export (the sample's fields, the chosen formats, the files' names);
    ValueError naming each option the formats refuse."""
    if quaternion_order not in ("wxyz", "xyzw"):
        raise ValueError(f"quaternion_order {quaternion_order!r}: expected wxyz or xyzw")
    rotation_names = orientation_columns(orientation)
    if orientation == "quaternion" and quaternion_order == "xyzw":
        rotation_names = ("qx", "qy", "qz", "qw")
    ext = ".csv" if delimiter == "csv" else ".txt"
    x_grid = {"x_grid": {"spacing_mm": manifest.scanner.x_spacing_mm}} if layout == "z_grid" else {}
    raw = {
        "sample_id": manifest.sample_id, "created": manifest.created, "material": manifest.material,
        "specimen": manifest.specimen, "weld": _weld(manifest), "sticker_diameter_mm": manifest.sticker_diameter_mm,
        "scanner": manifest.scanner,
        "profile_format": {"layout": layout, "delimiter": delimiter, "units": units, "time_unit": time_unit,
                           "no_return": no_return, "intensity_bits": intensity_bits, **x_grid},
        "pose_format": {"columns": ["time", "x", "y", "z", *rotation_names], "delimiter": delimiter, "units": units,
                        "time_unit": time_unit, "orientation": orientation, "angle_unit": angle_unit,
                        "header_lines": 1},
        "time_offset_s": time_offset_s,
        "setups": [{"name": s.name, "description": s.description,
                    "T_world_specimen_nominal": s.T_world_specimen_nominal,
                    "placement_tolerance_mm": s.placement_tolerance_mm,
                    "passes": [{"pass_id": p.pass_id, "direction": p.direction,
                                "profiles": f"profiles/{p.pass_id}{ext}{'.gz' if compress else ''}",
                                "poses": f"poses/{p.pass_id}{ext}"} for p in s.passes]}
                   for s in manifest.setups],
    }
    try:
        return CellDescription.model_validate(raw)
    except ValidationError as exc:
        raise ValueError("the cell logs cannot be written so: " + "; ".join(
            f"{'.'.join(map(str, e['loc']))}: {e['msg'].removeprefix('Value error, ')}" for e in exc.errors())
        ) from None


def _write_pass(sample_dir: Path, manifest: SampleManifest, file: str, cell: CellDescription, cp: CellPass,
                out: Path, *, compress: bool, pose_every: int) -> tuple[int, int]:
    """One pass's profile file and pose log, block by block; (profiles, poses) written."""
    reader = open_pass(sample_dir / file, pass_id=cp.pass_id)
    if not reader.has_poses:
        raise ValueError(f"pass {cp.pass_id}: {sample_dir / file} holds no flange pose per profile; the cell logs "
                         "need the robot's poses")
    poses = 0
    with _text_file(out / cp.profiles, compress) as profile_file, _text_file(out / cp.poses, False) as pose_file:
        pose_file.write(_join(cell.pose_format.columns, cell.pose_format.delimiter) + "\n")
        for start in range(0, reader.n_profiles, CHUNK_PROFILES):
            block = reader.read(start, min(start + CHUNK_PROFILES, reader.n_profiles))
            profile_file.writelines(_profile_lines(cell.profile_format, manifest, cp.pass_id, start, block))
            keep = [k for k in range(len(block.timestamp_s))
                    if (start + k) % pose_every == 0 or start + k == reader.n_profiles - 1]
            pose_file.writelines(_pose_lines(cell.pose_format, block.timestamp_s[keep] + cell.time_offset_s,
                                             block.T_world_flange[keep]))
            poses += len(keep)
    return reader.n_profiles, poses


@contextlib.contextmanager
def _text_file(path: Path, compress: bool) -> Iterator[TextIO]:
    """A new text file (UTF-8, ``\\n`` line ends); gzip-compressed without a time stamp when ``compress``."""
    with open(path, "xb") as raw:
        if not compress:
            with io.TextIOWrapper(raw, encoding="utf-8", newline="\n") as text:
                yield text
            return
        with gzip.GzipFile(filename="", mode="wb", fileobj=raw, compresslevel=6, mtime=0) as packed, \
                io.TextIOWrapper(packed, encoding="utf-8", newline="\n") as text:
            yield text


def _join(tokens, delimiter: str) -> str:
    return ("," if delimiter == "csv" else " ").join(tokens)


def _formatted(values: np.ndarray, fmt: str) -> np.ndarray:
    return np.char.mod(fmt, values)


def _profile_lines(fmt: ProfileFormat, manifest: SampleManifest, pass_id: str, start: int, block) -> list[str]:
    """One line per profile of ``block`` (a PassData) in ``fmt``'s layout; a missing return's X
    and Z are the no-return marker (``empty``: empty fields), its intensity 0."""
    n = manifest.scanner.points_per_profile
    returned = ~(np.isnan(block.x_mm) | np.isnan(block.z_mm))
    scale, length = _LENGTH_SCALE[fmt.units], _LENGTH_FORMAT[fmt.units]
    marker = np.nan if fmt.no_return in ("nan", "empty") else fmt.no_return
    z = np.where(returned, block.z_mm.astype(np.float64) * scale, marker)
    top = 2 ** fmt.intensity_bits - 1
    intensity = np.where(returned, np.rint(block.intensity.astype(np.float64) * (top / INTENSITY_MAX)), 0.0)
    if fmt.layout == "xzi":
        x = np.where(returned, block.x_mm.astype(np.float64) * scale, marker)
        values, formats = np.stack([x, z, intensity], axis=2).reshape(len(x), 3 * n), [length, length, "%d"] * n
    else:
        grid = (np.arange(n) - (n - 1) / 2) * manifest.scanner.x_spacing_mm
        off = returned & (np.abs(block.x_mm - grid) > GRID_TOLERANCE_MM)
        if off.any():
            row, col = (int(v[0]) for v in np.nonzero(off))
            raise ValueError(f"pass {pass_id}: profile {start + row}, point {col + 1}: "
                             f"X is {block.x_mm[row, col]:.4f} mm, "
                             f"not its grid's {grid[col]:.4f} mm; the z_grid layout holds scanners that report on a "
                             "fixed X grid: use layout xzi")
        values, formats = (np.concatenate([z, intensity], axis=1), [length] * n + ["%d"] * n) if fmt.intensities \
            else (z, [length] * n)
    time_format, time_scale = _TIME_FORMAT[fmt.time_unit]
    line = _join([time_format, *formats], fmt.delimiter) + "\n"
    rows = np.column_stack([block.timestamp_s * time_scale, values])
    lines = [line % tuple(row) for row in rows.tolist()]
    if fmt.no_return == "empty":  # an empty field for each missing X and Z
        lines = [text.replace("nan", "") for text in lines]
    return lines


def _pose_lines(fmt: PoseLogFormat, time_s: np.ndarray, T_world_flange: np.ndarray) -> list[str]:
    """One line per pose in ``fmt``'s columns: the robot-clock time, the flange's position and rotation."""
    rotation = Rotation.from_matrix(T_world_flange[:, :3, :3])
    time_format, time_scale = _TIME_FORMAT[fmt.time_unit]
    columns = {"time": _formatted(time_s * time_scale, time_format)}
    for k, name in enumerate("xyz"):
        columns[name] = _formatted(T_world_flange[:, k, 3] * _LENGTH_SCALE[fmt.units], _LENGTH_FORMAT[fmt.units])
    degrees = fmt.angle_unit != "rad"
    angle_format = "%.7f" if degrees else "%.9f"
    if fmt.orientation == "quaternion":
        values, angle_format = rotation.as_quat()[:, [3, 0, 1, 2]], "%.9f"  # scipy: scalar last
    elif fmt.orientation == "rotation-vector":
        values = rotation.as_rotvec(degrees=degrees)
    else:
        values = rotation.as_euler(scipy_euler_sequence(fmt.orientation), degrees=degrees)
    for name, column in zip(orientation_columns(fmt.orientation), values.T):
        columns[name] = _formatted(column, angle_format)
    return [_join(row, fmt.delimiter) + "\n" for row in zip(*(columns[c] for c in fmt.columns))]
