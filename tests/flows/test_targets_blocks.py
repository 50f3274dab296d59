"""The ``targets`` stage streams its pass in blocks of profiles (flows/stages/targets.py): its
outputs and metrics are the same bytes whatever the block size, and the same as
``tasks.targets.detect_targets`` on the whole pass at once. On passes of the ``ci`` sample: one
from each setup, with targets both found and rejected."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import flows.stages.targets as targets_stage
from data_catalog.manifests import load_manifest
from data_catalog.stages import load_arrays
from flows.stages.outputs import TARGETS
from flows.stages.passes import load_pass_points, open_entry
from flows.stages.runner import StageContext
from schemas.reconstruction import ReconstructionConfig
from tasks.targets import detect_targets

PASSES = ["top-L04", "bottom-W02"]  # 16 circles (3 rejected) on 939 profiles; 5 circles on 376 profiles


def _run(sample: Path, pass_id: str, out: Path, rows: int | None, monkeypatch) -> tuple[dict, dict[str, np.ndarray]]:
    """The stage's body on one pass in blocks of ``rows`` profiles: (metrics, output arrays)."""
    manifest = load_manifest(sample)
    entry = next(e for _, e in manifest.passes() if e.pass_id == pass_id)
    config = ReconstructionConfig()
    out.mkdir(parents=True)
    ctx = StageContext(out=out, sample_dir=sample, manifest=manifest, config=config, settings=config.targets,
                       entry=entry, inputs={})
    monkeypatch.setattr(targets_stage, "BLOCK_ROWS", rows)
    metrics = targets_stage.targets(ctx)
    return metrics, load_arrays(out / TARGETS.name, *TARGETS.arrays)


def _assert_same_bytes(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> None:
    assert a.keys() == b.keys()
    for name in a:
        assert a[name].dtype == b[name].dtype and a[name].shape == b[name].shape, name
        assert a[name].tobytes() == b[name].tobytes(), f"{name} differs"


# Blocks of 37 profiles: every circle's window (+-14 profiles) crosses a block's edge or reaches
# into its halo; of 1: every profile its own block.
@pytest.mark.parametrize("pass_id, rows", [("top-L04", 37), ("top-L04", 100), ("bottom-W02", 37), ("bottom-W02", 1)])
def test_the_stage_gives_the_same_bytes_in_any_blocks(ci_sample, pass_id, rows, tmp_path, monkeypatch):
    """Blocks of ``rows`` profiles against one block holding the whole pass."""
    manifest = load_manifest(ci_sample)
    entry = next(e for _, e in manifest.passes() if e.pass_id == pass_id)
    whole_metrics, whole = _run(ci_sample, pass_id, tmp_path / "whole", open_entry(ci_sample, entry).n_profiles,
                                monkeypatch)
    assert whole_metrics["targets"] >= 4
    metrics, arrays = _run(ci_sample, pass_id, tmp_path / "blocks", rows, monkeypatch)
    assert metrics == whole_metrics
    _assert_same_bytes(arrays, whole)
    # the blocks do split windows: some target lies within its window's reach (1.6 sticker radii)
    # of a block's edge
    reach = 1.6 * manifest.sticker_diameter_mm / 2 / manifest.grid_pitch_mm(entry)[0]
    row = whole["pixel"][:, 0]
    assert (np.abs(row - np.round(row / rows) * rows) < reach).any()


@pytest.mark.parametrize("pass_id", PASSES)
def test_the_stage_matches_detect_targets_on_the_whole_pass(ci_sample, pass_id, tmp_path, monkeypatch):
    manifest = load_manifest(ci_sample)
    entry = next(e for _, e in manifest.passes() if e.pass_id == pass_id)
    metrics, arrays = _run(ci_sample, pass_id, tmp_path / "stage", 37, monkeypatch)
    data, T, points = load_pass_points(ci_sample, manifest, entry)
    s = ReconstructionConfig().targets
    found = detect_targets(data.intensity, points, sticker_diameter_mm=manifest.sticker_diameter_mm,
                           sensor_origins_mm=T[:, :3, 3], max_rms_mm=s.max_rms_mm,
                           min_rim_coverage=s.min_rim_coverage, radius_tolerance=s.radius_tolerance,
                           rim_edge=s.rim_edge)
    assert (metrics["targets"], metrics["circles"], metrics["rejected"]) == (len(found.targets), found.n_circles,
                                                                           found.rejected)
    reader = open_entry(ci_sample, entry)
    assert tuple(arrays["grid_shape"]) == (reader.n_profiles, reader.n_columns)
    assert arrays["preview"].dtype == np.uint8 and 0 < arrays["preview"].shape[0] <= 640  # the report's picture
    found_arrays = {k: arrays[k] for k in ("centres", "normals", "rms_mm", "rim_coverage", "pixel")}
    _assert_same_bytes(found_arrays, {"centres": np.array([t.centre_mm for t in found.targets]),
                                "normals": np.array([t.normal for t in found.targets]),
                                "rms_mm": np.array([t.rms_mm for t in found.targets]),
                                "rim_coverage": np.array([t.rim_coverage for t in found.targets]),
                                "pixel": np.array([t.pixel for t in found.targets], dtype=np.float64)})
