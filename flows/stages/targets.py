"""Stage ``targets`` (per pass): the pass's sticker targets, 3-D centres in the coarse world frame."""

from __future__ import annotations

from typing import Any

import numpy as np

from flows.stages.outputs import PassTargets, TARGETS
from flows.stages.passes import load_pass_points, pass_view
from tasks.targets import detect_targets

__all__ = ["targets", "targets_view"]


def targets_view(manifest, entry) -> dict[str, Any]:
    return {**pass_view(manifest, entry), "sticker_diameter_mm": manifest.sticker_diameter_mm}


def targets(ctx) -> dict[str, Any]:
    s = ctx.settings
    data, T, points = load_pass_points(ctx.sample_dir, ctx.manifest, ctx.entry)
    found = detect_targets(data.intensity, points, sticker_diameter_mm=ctx.manifest.sticker_diameter_mm,
                           sensor_origins_mm=T[:, :3, 3], max_rms_mm=s.max_rms_mm,
                           min_rim_coverage=s.min_rim_coverage, radius_tolerance=s.radius_tolerance)
    if not found.targets:
        raise ValueError(f"pass {ctx.entry.pass_id}: no sticker targets found ({found.n_circles} circle candidates, "
                         f"rejected {found.rejected}); the pass cannot be registered")
    t = found.targets
    TARGETS.write(ctx.out, PassTargets(centres=np.array([x.centre_mm for x in t]), normals=np.array([x.normal for x in t]),
                                       rms_mm=np.array([x.rms_mm for x in t]),
                                       rim_coverage=np.array([x.rim_coverage for x in t]),
                                       pixel=np.array([x.pixel for x in t], dtype=np.float64)))
    return {"targets": len(t), "circles": found.n_circles, "rejected": found.rejected,
            "median_rms_mm": float(np.median([x.rms_mm for x in t]))}
