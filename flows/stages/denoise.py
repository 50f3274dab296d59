"""Stage ``denoise`` (per pass): ingest the pass (coarse alignment by the robot's poses) and remove
its statistical outliers."""

from __future__ import annotations

from typing import Any

import numpy as np

from flows.stages.outputs import CLOUD, DenoisedPass
from flows.stages.passes import load_pass_points
from tasks.denoise import remove_statistical_outliers

__all__ = ["denoise"]


def denoise(ctx) -> dict[str, Any]:
    s = ctx.settings
    _, T, points = load_pass_points(ctx.sample_dir, ctx.manifest, ctx.entry)
    result = remove_statistical_outliers(points, k=s.k, alpha=s.alpha, window_rows=s.window_rows,
                                         window_cols=s.window_cols)
    kept = np.where(result.keep[..., None], points, np.nan).astype(np.float32)
    CLOUD.write(ctx.out, DenoisedPass(points=kept, sensor_origins=T[:, :3, 3]))
    return {"points_in": int(np.isfinite(points).all(axis=-1).sum()), "points_out": int(result.keep.sum()),
            "removed": result.n_removed, "threshold_mm": result.threshold_mm}
