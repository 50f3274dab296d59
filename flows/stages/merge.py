"""Stage ``merge``: every pass into the common frame, merged by the box-grid filter, out of core.

Where the manifest says where the fixture put the specimen (``Setup.T_world_specimen_nominal``),
the zone around its weld lines (every point within ``merge.weld_zone_mm`` plus the setup's
placement tolerance of a line) stays at the fine resolution, flat or not (``placement.sample_weld_zone``).

Each pass is read in blocks of profiles; a block's points and normals go into the common frame and
are summed per cell (``tasks.merge.cell_sums``, a few times fewer records than points at the
paper's resolution); the partial sums are spilled to scratch files by slab of cells along x. Then
each slab is combined (``combine_cell_sums``) and appended to the output, slab after slab, in
(i, j, k) cell order. Memory: one block, the spill buffers and one slab, whatever the number of
passes or points.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from data_catalog.atomic import owner_tag
from flows.stages.outputs import CLOUD, MERGED, REFINED
from flows.stages.contracts import block_rows, zarr_array
from flows.stages.placement import sample_weld_zone
from tasks.merge import (CellSums, cell_index_of_keys, cell_sums, coarsen_flat_cells,
                         combine_cell_sums, transform_measured)

__all__ = ["merge"]


SLAB_CELLS = 128  # fine cells along x per spill file (rounded down to a whole number of coarse cells)
_BUFFER_RECORDS = 1 << 21  # spill buffers are flushed past this many records in all
_RECORD = np.dtype([("key", "<i8"), ("count", "<i8"), ("p", "<f8", 3), ("q", "<f8", 3)])


class _Spill:
    """Partial cell sums, appended per slab to files in ``folder`` (buffered, in arrival order)."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.buffers: dict[int, list[np.ndarray]] = {}
        self.buffered = 0
        self.records: dict[int, int] = {}

    def add(self, part: CellSums, slab: np.ndarray) -> None:
        rec = np.empty(len(part), _RECORD)
        rec["key"], rec["count"], rec["p"], rec["q"] = part.keys, part.counts, part.point_sums, part.normal_sums
        order = np.argsort(slab, kind="stable")
        bounds = np.flatnonzero(np.diff(slab[order])) + 1
        for chunk in np.split(order, bounds):
            if len(chunk):
                s = int(slab[chunk[0]])
                self.buffers.setdefault(s, []).append(rec[chunk])
                self.records[s] = self.records.get(s, 0) + len(chunk)
        self.buffered += len(rec)
        if self.buffered > _BUFFER_RECORDS:
            self.flush()

    def flush(self) -> None:
        for s, parts in self.buffers.items():
            with open(self.folder / f"{s}.bin", "ab") as f:
                for p in parts:
                    f.write(p.tobytes())
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
        for ref, T in zip(ctx.inputs["denoise"], T_all):
            points, normals = zarr_array(ref, CLOUD, "points"), zarr_array(ref, CLOUD, "normals")
            n, m = points.shape[:2]
            step = block_rows(m, chunk_profiles=points.chunks[0])
            for start in range(0, n, step):
                p, q = transform_measured(points[start:start + step], normals[start:start + step], T)
                points_in += len(p)
                part = cell_sums(p, q, cell_mm=s.cell_mm)
                spill.add(part, np.floor_divide(cell_index_of_keys(part.keys)[:, 0], slab_cells))
        out = MERGED.writer(ctx.out, chunk_rows=1 << 18)
        points_out = fine_cells = fine_out = zone_out = 0
        for part in spill.slabs():
            merged = combine_cell_sums(part, cell_mm=s.cell_mm)
            cloud = coarsen_flat_cells(merged, factor=s.coarse_factor, max_normal_deg=s.flat_normal_deg,
                                       max_deviation_mm=s.flat_deviation_mm, fine_zone=zone)
            out.append("points", cloud.points_mm)
            out.append("normals", cloud.normals.astype(np.float32))
            out.append("counts", cloud.counts.astype(np.int32))
            out.append("fine", cloud.fine)
            fine_cells += merged.n_points
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
