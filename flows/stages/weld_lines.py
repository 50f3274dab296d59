"""Where the weld lies in the reconstruction: the manifest's weld lines (specimen frame) carried
into the common frame through each setup's nominal placement and its first pass's pose. Used by
the stages that treat the weld apart (``merge`` keeps it fine, ``volume`` grades its elements)."""

from __future__ import annotations

from typing import Any

import numpy as np

from schemas.manifest import SampleManifest

__all__ = ["weld_lines_common", "weld_lines_view", "T_common_specimen", "weld_frame"]


def weld_lines_common(manifest: SampleManifest, T_common_pass: np.ndarray) -> list[tuple[np.ndarray, float]]:
    """Per setup that states its nominal placement and per weld line: the line's (k, 3) points in
    the common frame, mm, and the setup's placement tolerance, mm (how far the line may be off)."""
    lines = [np.asarray(line.points_mm, np.float64) for line in manifest.weld_lines()]
    return [(points @ T[:3, :3].T + T[:3, 3], float(setup.placement_tolerance_mm))
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


def weld_lines_view(manifest: SampleManifest, entry=None) -> dict[str, Any]:
    """What a stage that treats the weld apart reads of the manifest: the passes (in order), each
    setup's nominal placement and tolerance, and the weld lines (specimen frame, mm; a 1.0 and a
    1.1 manifest of one part give the same lines, hence the same key)."""
    return {"passes": [e.pass_id for _, e in manifest.passes()],
            "weld_lines_mm": [[list(p) for p in line.points_mm] for line in manifest.weld_lines()],
            "setups": [{"name": s.name, "passes": [e.pass_id for e in s.passes],
                        "T_world_specimen_nominal": s.T_world_specimen_nominal,
                        "placement_tolerance_mm": s.placement_tolerance_mm} for s in manifest.setups]}
