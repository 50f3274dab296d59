"""Stage ``merge``: every pass into the common frame, merged by the box-grid filter, out of core.

Where the manifest says where the fixture put the specimen (``Setup.T_world_specimen_nominal``),
the zone around its weld lines (every point within ``merge.weld_zone_mm`` plus the setup's
placement tolerance of a line) stays at the fine resolution, flat or not (``placement.sample_weld_zone``).

Each pass is read in blocks of profiles; a block's points and normals go into the common frame and
are summed per cell (``tasks.merge.cell_sums``, a few times fewer records than points at the
paper's resolution), two blocks at once on two threads; the partial sums are spilled to scratch
files by slab of cells along x, in the passes' and blocks' order whichever thread finishes first.
Then each slab is combined (``combine_cell_sums``), two at once, and appended to the output, slab
after slab, in (i, j, k) cell order. Memory: a few blocks, the spill buffers and a few slabs,
whatever the number of passes or points.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from data_catalog.atomic import owner_tag
from flows.stages.outputs import CLOUD, MERGED, REFINED
from flows.stages.contracts import block_rows, map_in_order, zarr_array
from flows.stages.placement import sample_weld_zone
from tasks.merge import (CellSums, cell_index_of_keys, cell_sums, coarsen_flat_cells,
                         combine_cell_sums, transform_measured)

__all__ = ["merge"]


SLAB_CELLS = 128  # fine cells along x per spill file (rounded down to a whole number of coarse cells)
BLOCK_WORKERS = 2  # blocks read and summed at once (zarr decompression and the Numba kernels release the GIL)
_BUFFER_RECORDS = 1 << 21  # spill buffers are flushed past this many records in all
_RECORD = np.dtype([("key", "<i8"), ("count", "<i8"), ("p", "<f8", 3), ("q", "<f8", 3)])


class _Spill:
    """Partial cell sums, appended per slab to files in ``folder`` (buffered, in arrival order)."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.buffers: dict[int, list[np.ndarray]] = {}
        self.buffered = 0
        self.records: dict[int, int] = {}

    @staticmethod
    def pieces(part: CellSums, slab: np.ndarray) -> list[tuple[int, np.ndarray]]:
        """A block's partial sums as spill records, by slab (ascending), each slab's in input order
        (on a block's own thread: the main thread only appends them)."""
        order = np.argsort(slab, kind="stable")
        rec = np.empty(len(part), _RECORD)
        rec["key"], rec["count"] = part.keys[order], part.counts[order]
        rec["p"], rec["q"] = part.point_sums[order], part.normal_sums[order]
        bounds = np.flatnonzero(np.diff(slab[order])) + 1
        return [(int(slab[order[a]]), chunk) for a, chunk in zip(np.r_[0, bounds], np.split(rec, bounds)) if len(chunk)]

    def add(self, pieces: list[tuple[int, np.ndarray]]) -> None:
        for s, chunk in pieces:
            self.buffers.setdefault(s, []).append(chunk)
            self.records[s] = self.records.get(s, 0) + len(chunk)
            self.buffered += len(chunk)
        if self.buffered > _BUFFER_RECORDS:
            self.flush()

    def flush(self) -> None:
        for s, parts in self.buffers.items():
            with open(self.folder / f"{s}.bin", "ab") as f:
                for p in parts:
                    f.write(memoryview(p).cast("B"))
        self.buffers, self.buffered = {}, 0

    def slabs(self):
        self.flush()
        for s in sorted(self.records):
            rec = np.fromfile(self.folder / f"{s}.bin", dtype=_RECORD)
            (self.folder / f"{s}.bin").unlink()
            yield CellSums(rec["key"], rec["count"], rec["p"], rec["q"])


def merge(ctx) -> dict[str, Any]:
    s = ctx.settings
    slab_cells = SLAB_CELLS // s.coarse_factor * s.coarse_factor  # a coarse cell never straddles two slabs
    T_all = REFINED.open(ctx.inputs["refine"]).T_common_pass
    zone = sample_weld_zone(ctx.manifest, T_all, s.weld_zone_mm, widened=True)
    points_in = 0
    with tempfile.TemporaryDirectory(prefix=f".scratch-{owner_tag()}-", dir=ctx.out.parent) as scratch:
        spill = _Spill(Path(scratch))

        def blocks():
            for ref, T in zip(ctx.inputs["denoise"], T_all):
                points, normals = zarr_array(ref, CLOUD, "points"), zarr_array(ref, CLOUD, "normals")
                n, m = points.shape[:2]
                step = block_rows(m, chunk_profiles=points.chunks[0])
                for start in range(0, n, step):
                    yield points, normals, slice(start, start + step), T

        def summed(block) -> tuple[int, list[tuple[int, np.ndarray]]]:
            points, normals, rows, T = block
            p, q = transform_measured(points[rows], normals[rows], T)
            part = cell_sums(p, q, cell_mm=s.cell_mm)
            return len(p), _Spill.pieces(part, np.floor_divide(cell_index_of_keys(part.keys)[:, 0], slab_cells))

        # two blocks read and summed at once, spilled in the passes' and blocks' order (same bytes)
        for count, pieces in map_in_order(summed, blocks(), workers=BLOCK_WORKERS):
            points_in += count
            spill.add(pieces)
        out = MERGED.writer(ctx.out, chunk_rows=1 << 18)
        points_out = fine_cells = fine_out = zone_out = 0

        def combined(part: CellSums):
            merged = combine_cell_sums(part, cell_mm=s.cell_mm)
            return merged.n_points, coarsen_flat_cells(merged, factor=s.coarse_factor, max_normal_deg=s.flat_normal_deg,
                                                       max_deviation_mm=s.flat_deviation_mm, fine_zone=zone)

        # two slabs combined at once, appended in slab order
        for n_fine, cloud in map_in_order(combined, spill.slabs(), workers=BLOCK_WORKERS):
            out.append("points", cloud.points_mm)
            out.append("normals", cloud.normals.astype(np.float32))
            out.append("counts", cloud.counts.astype(np.int32))
            out.append("fine", cloud.fine)
            fine_cells += n_fine
            points_out += len(cloud.points_mm)
            fine_out += int(cloud.fine.sum())
            zone_out += int(cloud.in_zone.sum())
        if points_out == 0:
            raise ValueError("no points to merge: every pass is empty after denoising")
        out.close()
    return {"points_in": int(points_in), "points_out": int(points_out), "fine_cells": int(fine_cells),
            "fine_points_out": int(fine_out), "coarse_points_out": int(points_out - fine_out),
            "weld_zone_points_out": int(zone_out),
            "weld_zones": [{"points_mm": [list(p) for p in z.points_mm], "radius_mm": z.radius_mm} for z in zone.zones]}
