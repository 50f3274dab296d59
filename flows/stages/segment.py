"""Stage ``segment`` (remove unwanted objects): keep the connected components that carry the
specimen's targets; the fixture goes."""

from __future__ import annotations

from typing import Any


from flows.stages.outputs import MERGED, REFINED, SPECIMEN, SpecimenCloud
from tasks.segment import keep_specimen_components

__all__ = ["segment"]


def segment(ctx) -> dict[str, Any]:
    merged = MERGED.open(ctx.inputs["merge"])
    reg = REFINED.open(ctx.inputs["refine"])
    anchors = reg.track_positions_mm[reg.specimen_track.astype(bool)]
    if len(anchors) == 0:
        raise ValueError("no target was seen in more than one setup: the specimen cannot be told from the fixture")
    result = keep_specimen_components(merged.points, link_mm=ctx.settings.link_mm, target_points_mm=anchors)
    keep = result.keep
    SPECIMEN.write(ctx.out, SpecimenCloud(points=merged.points[keep], sensor_positions=merged.sensor_positions[keep]))
    return {"points_in": int(len(keep)), "points_out": int(keep.sum()), "components": int(result.n_components),
            "kept_components": int(len(result.kept_labels))}
