"""A pass as the per-pass stages read it: its data, its sensor poses and its organized points in
the coarse world frame (the robot's logged poses, or else its nominal sweep)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from data_catalog.passes import PassData, read_pass
from schemas.manifest import PassEntry, SampleManifest
from tasks.ingest import profile_points, sensor_poses

__all__ = ["load_pass_points", "pass_view"]


def load_pass_points(sample_dir: Path, manifest: SampleManifest,
                     entry: PassEntry) -> tuple[PassData, np.ndarray, np.ndarray]:
    """The pass, T_world_sensor (profiles, 4, 4) and its points (profiles, columns, 3), mm."""
    data = read_pass(Path(sample_dir) / entry.file, pass_id=entry.pass_id)
    try:
        T = sensor_poses(manifest.scanner.T_flange_sensor, timestamp_s=data.timestamp_s,
                         T_world_flange=data.T_world_flange, motion=entry.nominal_motion)
    except ValueError as exc:
        raise ValueError(f"pass {entry.pass_id}: {exc}") from None
    return data, T, profile_points(data.x_mm, data.z_mm, T)


def pass_view(manifest: SampleManifest, entry: PassEntry | None) -> dict[str, Any]:
    """What a per-pass stage reads from the manifest besides the pass file: the scanner (hand-eye
    transform) and the pass's entry (its nominal motion)."""
    assert entry is not None
    return {"scanner": manifest.scanner.model_dump(mode="json"),
            "pass": entry.model_dump(mode="json", exclude={"file", "content_sha256"})}
