"""Placements: where the specimen, its weld lines and its weld zone lie in the reconstruction's
common frame. The manifest's weld lines (specimen frame) are carried into the common frame through
a setup's nominal placement and its first pass's pose; the frame the weld is measured in is the
first placed setup's (``weld_frame``), and the weld zone is the one around its lines
(``sample_weld_zone``): the merge keeps it at full resolution, the FE model names its surface, the
QA page draws it."""

from __future__ import annotations

from typing import Any

import numpy as np

from schemas.manifest import SampleManifest
from tasks.frames import apply
from tasks.weld_zone import WeldZone, weld_zone

__all__ = ["weld_lines_common", "T_common_specimen", "weld_frame", "sample_weld_zone", "model_weld_zone"]


def weld_lines_common(manifest: SampleManifest, T_common_pass: np.ndarray) -> list[tuple[np.ndarray, float]]:
    """Per setup that states its nominal placement and per weld line: the line's (k, 3) points in
    the common frame, mm, and the setup's placement tolerance, mm (how far the line may be off)."""
    lines = [np.asarray(line.points_mm, np.float64) for line in manifest.weld_lines()]
    return [(apply(T, points), float(setup.placement_tolerance_mm))
            for setup, T in T_common_specimen(manifest, T_common_pass) for points in lines]


def T_common_specimen(manifest: SampleManifest, T_common_pass: np.ndarray) -> list[tuple[Any, np.ndarray]]:
    """(setup, specimen frame -> common frame) for each setup that states its nominal placement:
    the placement through its first pass's pose."""
    index = {e.pass_id: k for k, (_, e) in enumerate(manifest.passes())}
    return [(setup, np.asarray(T_common_pass[index[setup.passes[0].pass_id]]) @ np.asarray(setup.T_world_specimen_nominal))
            for setup in manifest.setups if setup.T_world_specimen_nominal is not None]


def weld_frame(manifest: SampleManifest, T_common_pass: np.ndarray) -> np.ndarray | None:
    """Specimen frame -> common frame by the first setup that states its nominal placement: the
    frame the weld is measured in (stages weld, volume, qa_report). None: no setup is placed."""
    placed = T_common_specimen(manifest, T_common_pass)
    return placed[0][1] if placed else None


def sample_weld_zone(manifest: SampleManifest, T_common_pass: np.ndarray, radius_mm: float, *,
                     widened: bool = False) -> WeldZone:
    """The weld zone in the common frame: within ``radius_mm`` of the weld lines where the weld
    frame (the first placed setup) puts them; ``widened``: plus that setup's placement tolerance
    (the merge, which runs before the weld is found on the data). Empty where no setup is placed."""
    placed = T_common_specimen(manifest, T_common_pass)
    if not placed or radius_mm <= 0:
        return WeldZone(())
    setup, T = placed[0]
    radius = radius_mm + (float(setup.placement_tolerance_mm) if widened else 0.0)
    return weld_zone([apply(T, np.asarray(line.points_mm, np.float64)) for line in manifest.weld_lines()], radius)


def model_weld_zone(manifest: SampleManifest, T_common_pass: np.ndarray, config) -> WeldZone:
    """The weld zone the FE model names (``WELD_ZONE_SURFACE``: its boundary faces with their
    centroid in it) and the QA page colours (the same test on the mesh's faces): within
    ``volume.weld_zone_mm`` of the weld frame's lines, common frame. ``config``: the
    ReconstructionConfig."""
    return sample_weld_zone(manifest, T_common_pass, config.volume.weld_zone_mm)
