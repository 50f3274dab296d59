"""The per-pass stages stream their pass in blocks: peak memory does not grow with the pass's
length, and the outputs are the same bytes whatever the block size (and equal to the whole-pass
functions of ``tasks``)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from data_catalog.manifests import load_manifest
from data_catalog.stages import StageStore
from flows.stages import denoise as denoise_body
from flows.stages import run_stage, stage
from flows.stages.outputs import CLOUD, PREVIEW
from flows.stages.passes import load_pass_points
from schemas.reconstruction import ReconstructionConfig
from tasks.cells import grid_thinning_steps
from tasks.denoise import remove_statistical_outliers
from tests.flows.synthetic import write_plate_sample

ROOT = Path(__file__).resolve().parents[2]

# Runs one per-pass stage on the sample's first pass in a fresh process and prints its peak RSS.
_RUN_ONE = """
import json, resource, sys
from pathlib import Path
from data_catalog.manifests import load_manifest
from data_catalog.stages import StageStore
from flows.stages import run_stage, stage
from schemas.reconstruction import ReconstructionConfig
sample, store, name = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3]
m = load_manifest(sample / "manifest.json")
entry = m.passes()[0][1]
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
ref = run_stage(stage(name), store=StageStore(store), sample_dir=sample, manifest=m, config=ReconstructionConfig(),
                inputs={}, entry=entry)
print(json.dumps({"peak_kib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, "before_kib": before,
                  "metrics": ref.metrics}))
"""


@pytest.fixture(scope="module")
def plates(tmp_path_factory):
    """Two plates, 1,600 and 6,400 profiles of 2,048 points (3.3 M and 13.1 M points; 160 and
    640 mm of sweep at the paper's 0.02 x 0.1 mm grid)."""
    root = tmp_path_factory.mktemp("plates")
    return {n: write_plate_sample(root / f"plate_{n}", n) for n in (1600, 6400)}


def _peak_mib(sample: Path, store: Path, name: str) -> tuple[float, dict]:
    done = subprocess.run([sys.executable, "-c", _RUN_ONE, str(sample), str(store), name], cwd=ROOT,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    return result["peak_kib"] / 1024, result["metrics"]


@pytest.mark.slow
@pytest.mark.parametrize("name", ["denoise", "targets"])
def test_peak_memory_does_not_grow_with_pass_length(plates, tmp_path, name):
    short, short_metrics = _peak_mib(plates[1600], tmp_path / "short", name)
    long, long_metrics = _peak_mib(plates[6400], tmp_path / "long", name)
    if name == "denoise":
        assert long_metrics["points_in"] > 3.9 * short_metrics["points_in"]
    else:
        assert long_metrics["targets"] >= 3.5 * short_metrics["targets"] >= 3.5 * 5
    # Loading the whole pass would add ~13 M points x (24 B of float64 points + 24 B of outputs)
    # = ~600 MiB for the long one. Streamed, the peak is one block's (about 1 M points) either
    # way; 15 % leaves room for the allocator and zarr's buffers (measured: within 5 %).
    assert long < 1.15 * short, (name, short, long)


def test_denoise_blocks_give_the_whole_pass_bytes(tmp_path, monkeypatch):
    sample = write_plate_sample(tmp_path / "plate", 700, chunk_profiles=64)
    manifest = load_manifest(sample / "manifest.json")
    entry = manifest.passes()[0][1]
    config = ReconstructionConfig()
    outputs, previews = {}, {}
    for rows in (None, 64, 7):  # one block (the pass fits), blocks of a chunk, blocks of 7 profiles
        monkeypatch.setattr(denoise_body, "BLOCK_ROWS", rows)
        ref = run_stage(stage("denoise"), store=StageStore(tmp_path / f"store-{rows}"), sample_dir=sample,
                        manifest=manifest, config=config, inputs={}, entry=entry)
        outputs[rows] = CLOUD.read(ref)
        previews[rows] = PREVIEW.read(ref)
    for rows in (64, 7):
        for field in ("points", "normals", "sensor_origins"):
            assert np.array_equal(getattr(outputs[rows], field), getattr(outputs[None], field), equal_nan=True), \
                (rows, field)
    # the thinned copy the QA page reads: every a-th profile and b-th column of the outputs, whichever
    # rows each block began on (blocks of 7 and 64 against the copy's a)
    a, b = grid_thinning_steps(config.denoise.preview_cell_mm, manifest.grid_pitch_mm(entry))
    assert (a, b) == (3, 16) and previews[None].steps.tolist() == [a, b]  # profiles 0.1 mm apart, columns 0.02; 1 mm cells
    for rows in (None, 64, 7):
        assert np.array_equal(previews[rows].points, outputs[None].points[::a, ::b], equal_nan=True), rows
        assert np.array_equal(previews[rows].normals, outputs[None].normals[::a, ::b], equal_nan=True), rows
    # and the same points as the whole-pass function of tasks.denoise
    _, _, grid = load_pass_points(sample, manifest, entry)
    s = config.denoise
    whole = remove_statistical_outliers(grid, k=s.k, alpha=s.alpha, window_rows=s.window_rows,
                                        window_cols=s.window_cols)
    expected = np.where(whole.keep[..., None], grid, np.nan).astype(np.float32)
    assert np.array_equal(outputs[7].points, expected, equal_nan=True)
    assert 0 < whole.n_removed < 0.01 * whole.keep.size
    # the normals of the plate face up (toward the sensor above); the stickers' 0.1 mm rims tilt
    # the windows that straddle them, ~1.3 % of the points (measured: median 0.26 deg, 99 % 3.9 deg)
    normals = outputs[7].normals[np.isfinite(outputs[7].normals[..., 0])]
    tilt = np.degrees(np.arccos(np.clip(normals[:, 2], -1, 1)))
    assert normals[:, 2].min() > 0
    assert np.median(tilt) < 0.5 and np.quantile(tilt, 0.95) < 1.0, (np.median(tilt), np.quantile(tilt, 0.95))
