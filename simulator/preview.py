"""Pictures of a simulated sample for a person: a pass's intensity image with the true sticker
centres drawn on, and a top view of every pass's footprint per setup."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import zarr

from schemas.manifest import SampleManifest
from schemas.simulation import SimulationConfig
from schemas.truth import GroundTruth, PointLabel
from simulator.scanner import fan_directions
from tasks.arrays import distinct
from tasks.frames import apply, invert

__all__ = ["write_previews", "project_to_pass"]

_MAX_ROWS = 1600


def project_to_pass(points_world: np.ndarray, T_world_sensor: np.ndarray, x_spacing_mm: float,
                    reference_distance_mm: float, n_columns: int) -> np.ndarray:
    """Image coordinates (k, 2) = (profile, column), fractional, of world points (k, 3) in a pass
    taken at sensor poses (n, 4, 4); NaN where a point never crosses the laser plane."""
    T_sensor_world = invert(T_world_sensor)
    out = np.full((len(points_world), 2), np.nan)
    for k, p in enumerate(points_world):
        local = np.einsum("nij,j->ni", T_sensor_world[:, :3, :3], p) + T_sensor_world[:, :3, 3]
        y = local[:, 1]
        cross = np.flatnonzero(np.sign(y[:-1]) != np.sign(y[1:]))
        if cross.size == 0:
            continue
        i = cross[0]
        f = y[i] / (y[i] - y[i + 1])
        q = local[i] * (1 - f) + local[i + 1] * f
        column = q[0] / q[2] * reference_distance_mm / x_spacing_mm + (n_columns - 1) / 2
        out[k] = (i + f, column)
    return out


def _sticker_world(truth: GroundTruth, setup: str) -> np.ndarray:
    T = np.asarray(truth.T_world_specimen[setup])
    pts = []
    for s in truth.stickers:
        c = np.asarray(s.centre_mm)
        pts.append(apply(T, c) if s.on == "specimen" else c)
    return np.array(pts)


def _intensity_png(sample: Path, manifest: SampleManifest, truth: GroundTruth, pass_id: str, setup: str,
                   config: SimulationConfig, out: Path) -> None:
    store = zarr.open_group(str(sample / "passes" / f"{pass_id}.zarr"), mode="r")
    n, n_cols = store["intensity"].shape
    step = max(1, int(np.ceil(n / _MAX_ROWS)))
    image = np.asarray(store["intensity"][::step]).astype(np.float32)
    grey = np.clip(image / 1023 * 255, 0, 255).astype(np.uint8)
    # one physical pixel size on both axes, the long side at most about 2000 px
    row_mm = config.robot.profile_spacing_mm * step
    px_mm = max(row_mm, config.scanner.x_spacing_mm, n * config.robot.profile_spacing_mm / 2000)
    height = max(1, int(round(grey.shape[0] * row_mm / px_mm)))
    width = max(1, int(round(n_cols * config.scanner.x_spacing_mm / px_mm)))
    grey = cv2.resize(grey, (width, height), interpolation=cv2.INTER_AREA)
    colour = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    truth_store = zarr.open_group(str(sample / "truth" / "passes" / f"{pass_id}.zarr"), mode="r")
    T_true = np.asarray(truth_store["T_world_sensor"][...])
    reported = np.asarray(truth_store["label"][...]) == PointLabel.VALID
    seen = set(distinct(np.asarray(truth_store["sticker_id"][...])[reported]).tolist())
    uv = project_to_pass(_sticker_world(truth, setup), T_true, config.scanner.x_spacing_mm,
                         config.scanner.reference_distance_mm, config.scanner.points_per_profile)
    radius = max(3, int(round(config.stickers.diameter_mm / 2 / px_mm)))
    for (row, col), s in zip(uv, truth.stickers):
        if s.sticker_id in seen and np.isfinite(row) and 0 <= col < n_cols:
            centre = (int(round(col * width / n_cols)), int(round(row * height / n)))
            cv2.circle(colour, centre, radius, (0, 0, 255) if s.on == "specimen" else (255, 128, 0), 1)
            cv2.drawMarker(colour, centre, (0, 255, 0), cv2.MARKER_CROSS, 6, 1)
    colour = np.ascontiguousarray(np.rot90(colour))  # profiles left to right
    cv2.putText(colour, f"{pass_id}: intensity, true sticker centres (red: specimen, blue: fixture)",
                (5, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 255, 255), 1)
    cv2.imwrite(str(out), colour)


def _footprints_png(sample: Path, manifest: SampleManifest, truth: GroundTruth, setup: str,
                    config: SimulationConfig, out: Path) -> None:
    scale = 1600 / (config.specimen.length_mm + 2 * config.plan.margin_mm + 40)  # px per mm
    half_x = config.specimen.length_mm / 2 + config.plan.margin_mm + 20
    half_y = config.specimen.grip_width_mm / 2 + config.plan.margin_mm + 40
    width, height = int(2 * half_x * scale), int(2 * half_y * scale) + 40
    canvas = np.full((height, width, 3), 20, np.float32)
    fan = fan_directions(config.scanner.points_per_profile, config.scanner.x_spacing_mm,
                         config.scanner.reference_distance_mm)
    passes = [p for s in manifest.setups if s.name == setup for p in s.passes]
    palette = [(230, 159, 0), (86, 180, 233), (0, 158, 115), (240, 228, 66), (0, 114, 178), (213, 94, 0),
               (204, 121, 167), (200, 200, 200)]
    kernel = np.ones((5, 5), np.uint8)
    labels = []
    for index, p in enumerate(passes):
        store = zarr.open_group(str(sample / p.file), mode="r")
        truth_store = zarr.open_group(str(sample / "truth" / "passes" / f"{p.pass_id}.zarr"), mode="r")
        step = max(1, p.n_profiles // 400)
        col_step = max(1, config.scanner.points_per_profile // 128)
        z = np.asarray(store["z_mm"][::step, ::col_step], dtype=np.float64)
        T = np.asarray(truth_store["T_world_sensor"][::step])
        tan = fan[::col_step, 0] / fan[::col_step, 2]
        local = np.stack([z * tan[None, :], np.zeros_like(z), z], -1)
        pts = (np.einsum("nij,nkj->nki", T[:, :3, :3], local) + T[:, None, :3, 3]).reshape(-1, 3)
        pts = pts[np.isfinite(pts).all(1)]
        u = ((pts[:, 0] + half_x) * scale).astype(int)
        v = ((half_y - pts[:, 1]) * scale).astype(int)
        keep = (u >= 0) & (u < width) & (v >= 0) & (v < height)
        mask = np.zeros((height, width), np.uint8)
        mask[v[keep], u[keep]] = 1
        mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, kernel, iterations=2)
        colour = np.array(palette[index % len(palette)], np.float32)
        canvas[mask > 0] = 0.75 * canvas[mask > 0] + 0.25 * colour
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        cv2.drawContours(canvas, contours, -1, tuple(float(c) for c in colour), 1)
        labels.append((p.pass_id, (5 + 110 * (index % 14), height - 24 + 14 * (index // 14)), colour))
    canvas = np.clip(canvas, 0, 255).astype(np.uint8)
    for text, where, colour in labels:
        cv2.putText(canvas, text, where, cv2.FONT_HERSHEY_SIMPLEX, 0.4, tuple(int(c) for c in colour), 1)
    for c in _sticker_world(truth, setup):
        cv2.circle(canvas, (int((c[0] + half_x) * scale), int((half_y - c[1]) * scale)),
                   max(2, int(config.stickers.diameter_mm / 2 * scale)), (255, 255, 255), 1)
    cv2.putText(canvas, f"setup {setup}: footprints of {len(passes)} passes (world xy, from above); stickers white",
                (5, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1)
    cv2.imwrite(str(out), canvas)


def write_previews(sample: Path, manifest: SampleManifest, truth: GroundTruth, config: SimulationConfig) -> None:
    out = sample / "preview"
    out.mkdir(exist_ok=True)
    for setup in manifest.setups:
        first = setup.passes[0].pass_id
        _intensity_png(sample, manifest, truth, first, setup.name, config, out / f"{first}_intensity.png")
        _footprints_png(sample, manifest, truth, setup.name, config, out / f"footprints_{setup.name}.png")
