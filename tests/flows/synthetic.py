"""A synthetic one-pass sample of any length: a flat plate seen head-on by a 2048-point line
scanner at the paper's grid (0.02 mm along the line, 0.1 mm between profiles), with sticker
targets every 30 mm along the sweep, range noise and a few outliers. For tests that need passes
of chosen lengths (memory against pass length, block-wise against whole-pass results)."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from data_catalog.manifests import write_manifest
from data_catalog.passes import PassWriter
from schemas.manifest import SampleManifest

__all__ = ["write_plate_sample"]

COLUMNS = 2048
X_SPACING_MM = 0.02
SPEED_MM_S, RATE_HZ = 15.0, 150.0  # 0.1 mm between profiles
STANDOFF_MM = 200.0
STICKER_DIAMETER_MM = 10.0


def _manifest(sample_id: str, n_profiles: int) -> SampleManifest:
    # sensor looking straight down: S's x along world x, S's z along world -z, sweep along world y
    T_down = [[1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, -5.0], [0.0, 0.0, -1.0, STANDOFF_MM], [0.0, 0.0, 0.0, 1.0]]
    duration = n_profiles / RATE_HZ
    entry = {"pass_id": "plate", "file": "passes/plate.zarr", "direction": "along-length", "n_profiles": n_profiles,
             "duration_s": duration, "has_profile_poses": False,
             "nominal_motion": {"T_world_flange_start": T_down, "direction_world": [0.0, 1.0, 0.0],
                                "speed_mm_s": SPEED_MM_S, "profile_rate_hz": RATE_HZ,
                                "length_mm": duration * SPEED_MM_S}}
    return SampleManifest.model_validate({
        "schema_version": "1.0", "units": "mm", "sample_id": sample_id, "created": datetime(2026, 11, 23, tzinfo=UTC),
        "specimen": {"length_mm": 570, "grip_width_mm": 100, "gauge_width_mm": 70, "gauge_length_mm": 150,
                     "transition_radius_mm": 100, "thickness_mm": 20},
        "weld": {}, "sticker_diameter_mm": STICKER_DIAMETER_MM,
        "scanner": {"model": "synthetic", "points_per_profile": COLUMNS, "x_spacing_mm": X_SPACING_MM,
                    "z_resolution_mm": 0.004, "reference_distance_mm": STANDOFF_MM, "z_range_mm": [100.0, 300.0],
                    "camera_offset_mm": [60.0, 0.0, 0.0],
                    "T_flange_sensor": [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0],
                                        [0.0, 0.0, 0.0, 1.0]]},
        "setups": [{"name": "top", "passes": [entry]}]})


def write_plate_sample(out: Path, n_profiles: int, *, seed: int = 0, chunk_profiles: int = 256) -> Path:
    """Write the sample folder ``out`` (manifest + one pass of ``n_profiles`` profiles)."""
    out = Path(out)
    (out / "passes").mkdir(parents=True)
    rng = np.random.default_rng(seed)
    x = (np.arange(COLUMNS) - COLUMNS / 2) * X_SPACING_MM
    radius = STICKER_DIAMETER_MM / 2
    writer = PassWriter(out / "passes" / "plate.zarr", pass_id="plate", n_profiles=n_profiles, n_columns=COLUMNS,
                        chunk_profiles=chunk_profiles, with_poses=False)
    for start in range(0, n_profiles, chunk_profiles):
        rows = np.arange(start, min(start + chunk_profiles, n_profiles))
        y = rows * SPEED_MM_S / RATE_HZ
        # stickers every 30 mm along y, alternating 8 mm either side of the line's centre
        k = np.round((y - 15.0) / 30.0)
        cy, cx = 15.0 + 30.0 * k, np.where(k % 2 == 0, 8.0, -8.0)
        dx, dy = x[None, :] - cx[:, None], y[:, None] - cy[:, None]
        on = dx**2 + dy**2 < radius**2
        # the share of each point's footprint (0.02 x 0.1 mm) on the sticker: rims read partly bright
        offsets = (np.arange(4) + 0.5) / 4 - 0.5
        share = sum(((dx + a * X_SPACING_MM) ** 2 + (dy + b * SPEED_MM_S / RATE_HZ) ** 2 < radius**2)
                    for a in offsets for b in offsets) / 16.0
        height = np.where(on, 0.1, 0.0) + rng.normal(0.0, 0.006, on.shape)
        z = STANDOFF_MM - height
        outlier = rng.random(on.shape) < 0.002
        z[outlier] -= rng.uniform(0.3, 4.0, int(outlier.sum()))
        intensity = np.round(300 + 600 * share).astype(np.int64) + rng.integers(-20, 21, on.shape)
        missing = rng.random(on.shape) < 0.002
        xs = np.where(missing, np.nan, np.broadcast_to(x, on.shape))
        z[missing] = np.nan
        intensity[missing] = 0
        writer.write(start, x_mm=xs, z_mm=z, intensity=intensity, timestamp_s=rows / RATE_HZ)
    writer.close()
    write_manifest(out / "manifest.json", _manifest(out.name.replace("_", "-") or "plate", n_profiles))
    return out
