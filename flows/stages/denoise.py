"""Stage ``denoise`` (per pass): ingest the pass (coarse alignment by the robot's poses), remove its
statistical outliers and give every kept point its normal, streaming the pass in blocks.

Two passes over the pass file: the first computes each point's mean neighbour distance block by
block (kept in a scratch file beside the build folder) and the pass's statistics; the second
applies the threshold, fits the normals (their windows reach into the neighbouring blocks' rows)
and writes the outputs chunk by chunk. Peak memory is that of one block, whatever the pass's
length; the outputs are the same bytes for any block size.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from data_catalog.atomic import owner_tag
from data_catalog.scans import read_scan
from flows.stages.outputs import CLOUD, PREVIEW, PassPreview
from flows.stages.passes import block_rows, open_entry, pass_blocks
from schemas.manifest import ScanEntry
from tasks.cells import grid_thinning_steps
from tasks.consistency import MotionCheck, chunk_jumps, profile_steps
from tasks.denoise import DistanceStats, check_window, mean_knn_distance, relative_neighbour_distance
from tasks.mesh import estimate_normals
from tasks.normals import grid_normals, normal_window

__all__ = ["denoise"]

# Block size override for tests (profiles per block); None: ``block_rows``.
BLOCK_ROWS: int | None = None
# An imported scan's sensor, as the stored ``sensor_origins``: this far from each point along the
# scan's view direction (a direction, not a position: a range scan's own sensor is not recorded)
SCAN_SENSOR_DISTANCE_MM = 1.0e4
_SCAN_CHUNK_ROWS = 1 << 16


def _denoise_scan(ctx) -> dict[str, Any]:
    """An imported scan (no grid): into the coarse world frame by its given pose (none: its own
    frame), statistical outliers removed on its k nearest points (each point's mean distance to
    them relative to theirs: ``tasks.denoise.relative_neighbour_distance``), a normal per kept point from its
    ``scan_normal_neighbours`` nearest, turned toward the scan's view direction. Written as a
    (points, 1) grid: one point per row, its row's sensor origin far along the view direction."""
    s = ctx.settings
    scan = read_scan(ctx.sample_dir / ctx.entry.file, pass_id=ctx.entry.pass_id)
    T = scan.T_world_pass if scan.T_world_pass is not None else np.eye(4)
    points = scan.points_mm @ T[:3, :3].T + T[:3, 3]
    view = T[:3, :3] @ np.asarray(ctx.entry.view_direction, dtype=np.float64)
    ratios = relative_neighbour_distance(points, k=s.k)
    stats = DistanceStats()
    stats.add(ratios)
    threshold = stats.threshold_mm(s.alpha)  # of the ratio here
    kept = points[~(ratios > threshold)]  # NaN (too few points to judge): kept
    if len(kept) < s.scan_normal_neighbours:
        raise ValueError(f"pass {ctx.entry.pass_id}: {len(kept)} points left after the outliers went, fewer than "
                         f"denoise.scan_normal_neighbours {s.scan_normal_neighbours}; a scan needs more to register")
    sensors = kept + SCAN_SENSOR_DISTANCE_MM * view
    normals = estimate_normals(kept, sensors, k=s.scan_normal_neighbours)
    out = CLOUD.writer(ctx.out, chunk_rows=_SCAN_CHUNK_ROWS)
    out.create("points", (len(kept), 1, 3), np.float32)
    out.create("normals", (len(kept), 1, 3), np.float32)
    out.create("sensor_origins", (len(kept), 3), np.float64)
    out.write("points", 0, kept[:, None, :])
    out.write("normals", 0, normals[:, None, :])
    out.write("sensor_origins", 0, sensors)
    out.close()
    PREVIEW.write(ctx.out, PassPreview(points=np.zeros((0, 0, 3), np.float32), normals=np.zeros((0, 0, 3), np.float32),
                                       steps=np.zeros(2, np.int64)))  # no grid to thin by: the page reads the scan
    return {"points_in": int(len(points)), "points_out": int(len(kept)), "removed": int(len(points) - len(kept)),
            "threshold_ratio": threshold, "pose": "given" if scan.T_world_pass is not None else "none"}


def denoise(ctx) -> dict[str, Any]:
    if isinstance(ctx.entry, ScanEntry):
        return _denoise_scan(ctx)
    s = ctx.settings
    check_window(k=s.k, window_rows=s.window_rows, window_cols=s.window_cols)
    reader = open_entry(ctx.sample_dir, ctx.entry)
    n, m = reader.n_profiles, reader.n_columns
    rows = BLOCK_ROWS or block_rows(m, chunk_profiles=reader.chunk_profiles)
    pitch = ctx.manifest.grid_pitch_mm(ctx.entry)
    nr, nc = normal_window(s.normal_window_mm, pitch)
    stats = DistanceStats()
    motion = MotionCheck(ctx.entry.pass_id, ctx.entry.nominal_motion.speed_mm_s)
    steps = np.full(max(n - 1, 0), np.nan)  # the surface's step from each profile to the next
    points_in = 0
    reference = None  # the sensor at the first profile: normals sum coordinates relative to it
    with tempfile.TemporaryDirectory(prefix=f".scratch-{owner_tag()}-", dir=ctx.out.parent) as scratch:
        distances = Path(scratch) / "mean_distance.f8"
        with open(distances, "wb") as f:
            for block in pass_blocks(ctx.sample_dir, ctx.manifest, ctx.entry, halo_rows=max(s.window_rows, 1), rows=rows,
                                     reader=reader):
                md = mean_knn_distance(block.points, k=s.k, window_rows=s.window_rows, window_cols=s.window_cols,
                                       rows=block.core, pitch_mm=pitch)
                stats.add(md)
                core = block.data
                motion.feed(block.core_start, core.timestamp_s[block.core],
                            None if core.T_world_flange is None else core.T_world_flange[block.core])
                last = min(block.core.stop + 1, block.stop - block.start)  # one row past the core
                steps[block.core_start:block.core_start + last - block.core.start - 1] = \
                    profile_steps(core.z_mm[block.core.start:last])
                if reference is None:
                    reference = block.T_world_sensor[0, :3, 3].copy()
                points_in += int(np.isfinite(block.points[block.core]).all(axis=-1).sum())
                f.write(md.tobytes())
        threshold = stats.threshold_mm(s.alpha)
        out = CLOUD.writer(ctx.out, chunk_rows=reader.chunk_profiles)
        out.create("points", (n, m, 3), np.float32)
        out.create("normals", (n, m, 3), np.float32)
        out.create("sensor_origins", (n, 3), np.float64)
        # the thinned copy for the QA page: every a-th profile from the first, every b-th column
        a, b = grid_thinning_steps(s.preview_cell_mm, pitch)
        preview = PREVIEW.writer(ctx.out, chunk_rows=max(1, reader.chunk_profiles // a))
        preview.create("points", (-(-n // a), -(-m // b), 3), np.float32)
        preview.create("normals", (-(-n // a), -(-m // b), 3), np.float32)
        preview.create("steps", (2,), np.int64)
        preview.write("steps", 0, np.array([a, b], np.int64))
        kept_total = 0
        for block in pass_blocks(ctx.sample_dir, ctx.manifest, ctx.entry, halo_rows=nr, rows=rows, reader=reader):
            md = np.fromfile(distances, dtype=np.float64, count=(block.stop - block.start) * m,
                             offset=block.start * m * 8).reshape(-1, m)
            keep = np.isfinite(md) & (md <= threshold)
            kept = np.where(keep[..., None], block.points, np.nan)
            normals = grid_normals(kept, block.T_world_sensor[:, :3, 3], window_rows=nr, window_cols=nc,
                                   min_points=s.normal_min_points, reference_mm=reference, rows=block.core)
            out.write("points", block.core_start, kept[block.core])
            out.write("normals", block.core_start, normals)
            out.write("sensor_origins", block.core_start, block.T_world_sensor[block.core, :3, 3])
            first = -(-block.core_start // a) * a - block.core_start  # the core's first row on the copy's grid
            if first < len(normals):
                preview.write("points", (block.core_start + first) // a, kept[block.core][first::a, ::b])
                preview.write("normals", (block.core_start + first) // a, normals[first::a, ::b])
            kept_total += int(keep[block.core].sum())
        out.close()
        preview.close()
    return {"points_in": points_in, "points_out": kept_total, "removed": points_in - kept_total,
            "threshold_mm": threshold, "normal_window": [2 * nr + 1, 2 * nc + 1],
            "checks": {"motion": motion.summary(), "chunk_jumps": chunk_jumps(steps, reader.chunk_profiles)}}
