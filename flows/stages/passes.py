"""A pass as the per-pass stages read it, block by block: its data, its sensor poses and its
organized points in the coarse world frame (the robot's logged poses, or else its nominal sweep).

A per-pass stage never holds its whole pass: ``pass_blocks`` yields runs of profiles of a fixed
number of points (whatever the pass's length) with the halo rows a window around each profile
needs, so a stage's peak memory is that of one block.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from data_catalog.passes import PassData, PassFormatError, PassReader, open_pass
from flows.stages.contracts import BLOCK_POINTS, block_rows
from schemas.manifest import PassEntry, SampleManifest
from tasks.ingest import profile_points, sensor_poses

__all__ = ["BLOCK_POINTS", "PassBlock", "open_entry", "pass_blocks", "block_rows", "load_pass_points"]

@dataclass(frozen=True)
class PassBlock:
    """Profiles ``start`` to ``stop`` of a pass (``data``, ``T_world_sensor`` (rows, 4, 4),
    ``points`` (rows, columns, 3) float64 mm, coarse world frame, NaN: no return), of which rows
    ``core`` (relative to ``start``) are the block's own and the others its halo."""

    start: int
    stop: int
    core: slice
    data: PassData
    T_world_sensor: np.ndarray
    points: np.ndarray

    @property
    def core_start(self) -> int:
        return self.start + self.core.start

    @property
    def core_stop(self) -> int:
        return self.start + self.core.stop


def open_entry(sample_dir: Path, entry: PassEntry) -> PassReader:
    """The pass store of ``entry``, checked against what the manifest says of it: logged flange
    poses present exactly when ``has_profile_poses`` says so (missing ones would silently fall back
    to the nominal sweep), and profile times spanning the pass's ``duration_s`` (times in ms, or
    another pass's, are not the robot's)."""
    reader = open_pass(Path(sample_dir) / entry.file, pass_id=entry.pass_id)
    where = f"pass {entry.pass_id} ({reader.path})"
    if reader.has_poses != entry.has_profile_poses:
        raise PassFormatError(f"{where}: the manifest says has_profile_poses {str(entry.has_profile_poses).lower()}, "
                              f"but the store {'holds' if reader.has_poses else 'has no'} T_world_flange; expected "
                              "both to agree")
    times = reader.read_array("timestamp_s", [0, reader.n_profiles - 1])
    span = float(times[-1] - times[0])
    if np.all(np.isfinite(times)) and abs(span - entry.duration_s) > 0.1 * entry.duration_s + 0.5:
        raise PassFormatError(f"{where}: timestamp_s spans {span:g} s, but the manifest's duration_s is "
                              f"{entry.duration_s:g} s; expected seconds since the pass started")
    return reader


def _block(reader: PassReader, manifest: SampleManifest, entry: PassEntry, start: int, stop: int,
           core: slice) -> PassBlock:
    data = reader.read(start, stop)
    try:
        T = sensor_poses(manifest.scanner.T_flange_sensor, timestamp_s=data.timestamp_s,
                         T_world_flange=data.T_world_flange, motion=entry.nominal_motion)
    except ValueError as exc:
        raise ValueError(f"pass {entry.pass_id}: profiles {start}-{stop - 1}: {exc}") from None
    return PassBlock(start=start, stop=stop, core=core, data=data, T_world_sensor=T,
                     points=profile_points(data.x_mm, data.z_mm, T))


def pass_blocks(sample_dir: Path, manifest: SampleManifest, entry: PassEntry, *, halo_rows: int = 0,
                rows: int | None = None, reader: PassReader | None = None) -> Iterator[PassBlock]:
    """The pass in consecutive blocks of ``rows`` profiles (default: ``block_rows``), each with up
    to ``halo_rows`` profiles before and after it (fewer at the pass's ends)."""
    reader = reader or open_entry(sample_dir, entry)
    n = reader.n_profiles
    step = rows or block_rows(reader.n_columns, chunk_profiles=reader.chunk_profiles)
    for core_start in range(0, n, step):
        core_stop = min(core_start + step, n)
        start, stop = max(0, core_start - halo_rows), min(n, core_stop + halo_rows)
        yield _block(reader, manifest, entry, start, stop, slice(core_start - start, core_stop - start))


def load_pass_points(sample_dir: Path, manifest: SampleManifest,
                     entry: PassEntry) -> tuple[PassData, np.ndarray, np.ndarray]:
    """The whole pass, T_world_sensor (profiles, 4, 4) and its points (profiles, columns, 3), mm.
    For tests and tools on small passes; the stages stream blocks (``pass_blocks``)."""
    reader = open_entry(sample_dir, entry)
    block = _block(reader, manifest, entry, 0, reader.n_profiles, slice(0, reader.n_profiles))
    return block.data, block.T_world_sensor, block.points
