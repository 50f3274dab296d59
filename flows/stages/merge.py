"""Stage ``merge``: every pass into the common frame, merged by the box-grid filter."""

from __future__ import annotations

from typing import Any

import numpy as np

from flows.stages.outputs import CLOUD, MERGED, MergedCloud, REFINED
from tasks.merge import merge_box_grid

__all__ = ["merge"]


def merge(ctx) -> dict[str, Any]:
    T_all = REFINED.open(ctx.inputs["refine"]).T_common_pass
    points, sensors = [], []
    for ref, T in zip(ctx.inputs["denoise"], T_all):
        cloud = CLOUD.read(ref)
        grid = cloud.points.astype(np.float64)
        valid = np.isfinite(grid).all(axis=-1)
        rows = np.nonzero(valid)[0]
        points.append(grid[valid] @ T[:3, :3].T + T[:3, 3])
        sensors.append(cloud.sensor_origins[rows] @ T[:3, :3].T + T[:3, 3])
    result = merge_box_grid(np.concatenate(points), cell_mm=ctx.settings.cell_mm,
                            sensor_positions_mm=np.concatenate(sensors))
    MERGED.write(ctx.out, MergedCloud(points=result.points_mm, sensor_positions=result.sensor_positions_mm,
                                      counts=result.counts))
    return {"points_in": int(sum(len(p) for p in points)), "points_out": result.n_points}
