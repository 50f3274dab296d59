"""Stage ``segment`` (remove unwanted objects): keep the connected components that carry the
specimen's targets; the fixture goes. Components come from the occupied cells of a grid
(``tasks.segment``): memory follows the merged points, not pairs of them."""

from __future__ import annotations

from typing import Any

import numpy as np

from flows.stages.contracts import zarr_array
from flows.stages.outputs import MERGED, REFINED, SPECIMEN
from tasks.segment import keep_specimen_components

__all__ = ["segment"]

_ROWS = 1 << 20  # merged points per block written


def segment(ctx) -> dict[str, Any]:
    reg = REFINED.open(ctx.inputs["refine"])
    anchors = reg.track_positions_mm[reg.specimen_track.astype(bool)]
    if len(anchors) == 0:
        raise ValueError("no target was seen in more than one setup: the specimen cannot be told from the fixture")
    points = zarr_array(ctx.inputs["merge"], MERGED, "points")
    normals = zarr_array(ctx.inputs["merge"], MERGED, "normals")
    fine = zarr_array(ctx.inputs["merge"], MERGED, "fine")
    all_points = np.asarray(points[...])  # labelling needs every point; normals and zones are read by block
    result = keep_specimen_components(all_points, link_mm=ctx.settings.link_mm, target_points_mm=anchors)
    keep = result.keep
    out = SPECIMEN.writer(ctx.out, chunk_rows=1 << 18)
    kept = no_normal = 0
    for start in range(0, len(keep), _ROWS):
        rows = slice(start, start + _ROWS)
        p, q = all_points[rows], np.asarray(normals[rows])
        take = keep[rows] & np.isfinite(q).all(axis=1)  # a cell whose normals cancelled has none: left out
        no_normal += int(np.count_nonzero(keep[rows]) - np.count_nonzero(take))
        out.append("points", p[take])
        out.append("normals", q[take])
        out.append("fine", np.asarray(fine[rows])[take])
        kept += int(take.sum())
    out.close()
    return {"points_in": int(len(keep)), "points_out": kept, "without_normal": no_normal,
            "components": int(result.n_components), "kept_components": int(len(result.kept_labels))}
