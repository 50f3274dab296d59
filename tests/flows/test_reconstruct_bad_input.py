"""Bad input to the reconstruction: a clear error naming the pass or field, and earlier outputs
left intact."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr

from data_catalog.manifests import ManifestError
from tests.flows.samples import copy_sample
from tests.flows.samples import as_published

REPO = Path(__file__).resolve().parents[2]
CI_CONFIG = str(REPO / "deploy" / "configs" / "ci.yaml")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")


def _reconstruct(sample, out, config=CI_CONFIG):
    from flows.reconstruct import reconstruct_sample

    return as_published(reconstruct_sample(str(sample), str(out), config))


def _tree(path: Path) -> dict[str, bytes]:
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


def test_missing_and_truncated_pass_files_are_named_and_earlier_outputs_kept(ci_sample, tmp_path):
    from flows.reconstruct import ReconstructionFailed

    keep = ["top-L01", "top-L02", "top-L03"]
    sample = copy_sample(ci_sample, tmp_path / "s", keep)
    out = tmp_path / "out"
    # first, a stage that succeeds, to see it survive the failures below
    (out / "stages").mkdir(parents=True)
    marker = out / "stages" / "earlier.txt"
    marker.write_text("an earlier result")
    shutil.rmtree(sample / "passes" / "top-L02.zarr")
    with pytest.raises(ReconstructionFailed, match=r"pass top-L02: .*top-L02.zarr does not exist"):
        _reconstruct(sample, out)
    shutil.copytree(ci_sample / "passes" / "top-L02.zarr", sample / "passes" / "top-L02.zarr")
    chunk = sorted((sample / "passes" / "top-L03.zarr" / "z_mm" / "c").rglob("*"))[-1]
    chunk.write_bytes(chunk.read_bytes()[:100])
    with pytest.raises(ReconstructionFailed, match=r"pass top-L03: passes/top-L03.zarr does not match the manifest"):
        _reconstruct(sample, out)
    assert marker.read_text() == "an earlier result"
    # the passes that were fine were denoised, and their results stay in the store
    assert len(list((out / "stages" / "denoise").glob("*/record.json"))) >= 1


def test_truncated_pass_without_a_manifest_hash_is_caught_by_the_reader(ci_sample, tmp_path):
    from flows.reconstruct import ReconstructionFailed

    sample = copy_sample(ci_sample, tmp_path / "s", ["top-L01", "top-L02"])
    manifest = json.loads((sample / "manifest.json").read_text())
    for p in manifest["setups"][0]["passes"]:
        p["content_sha256"] = None
    (sample / "manifest.json").write_text(json.dumps(manifest))
    chunk = sorted((sample / "passes" / "top-L02.zarr" / "intensity" / "c").rglob("*"))[-1]
    chunk.unlink()
    with pytest.raises(ReconstructionFailed, match=r"pass top-L02 .*'intensity' has \d+ of \d+ chunks on disk; the file is truncated"):
        _reconstruct(sample, tmp_path / "out")


@pytest.mark.parametrize(("edit", "message"), [
    (lambda m: m.update(units="inch"), r"units: Input should be 'mm'"),
    (lambda m: m.update(operator="bob"), r"operator: Extra inputs are not permitted"),
])
def test_bad_manifest_is_refused_before_any_work(ci_sample, tmp_path, edit, message):
    sample = copy_sample(ci_sample, tmp_path / "s", ["top-L01"])
    manifest = json.loads((sample / "manifest.json").read_text())
    edit(manifest)
    (sample / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ManifestError, match=message):
        _reconstruct(sample, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_a_pass_without_stickers_is_named(ci_sample, tmp_path):
    from flows.reconstruct import ReconstructionFailed

    sample = copy_sample(ci_sample, tmp_path / "s", ["top-L01", "top-L02"])
    manifest = json.loads((sample / "manifest.json").read_text())
    entry = next(p for p in manifest["setups"][0]["passes"] if p["pass_id"] == "top-L02")
    entry["content_sha256"] = None
    (sample / "manifest.json").write_text(json.dumps(manifest))
    intensity = zarr.open_array(str(sample / "passes" / "top-L02.zarr" / "intensity"), mode="r+")
    flat = np.asarray(intensity[...])
    intensity[...] = np.where(flat > 0, 380, 0).astype(np.uint16)  # stickers painted over
    with pytest.raises(ReconstructionFailed, match=r"pass top-L02: no sticker targets found"):
        _reconstruct(sample, tmp_path / "out")


def test_too_few_common_stickers_names_the_pair_and_the_lost_passes(ci_sample, tmp_path):
    from flows.stages import StageFailed

    # top-L04 and top-W01 overlap, but share only one sticker that both see whole
    sample = copy_sample(ci_sample, tmp_path / "s", ["top-L04", "top-W01"])
    with pytest.raises(StageFailed) as info:
        _reconstruct(sample, tmp_path / "out")
    assert info.value.stage == "registration" and not info.value.retryable
    text = str(info.value)
    assert "passes ['top-W01'] share no chain of 3+ common targets" in text
    assert "top-L04|top-W01 (1)" in text


@pytest.mark.parametrize("where", [".", "passes/{store}/run", "passes/{store}", "truth/run", "manifest.json/run"])
def test_a_run_folder_inside_the_samples_own_inputs_is_refused_and_nothing_is_written(ci_sample, tmp_path, where):
    from data_catalog.hashing import sha256_tree
    from tests.flows.cli import run_cli

    sample = tmp_path / "sample"
    shutil.copytree(ci_sample, sample)
    store = sorted((sample / "passes").iterdir())[0].name
    before = sha256_tree(sample)
    out = sample / where.format(store=store)
    done = run_cli("reconstruct", str(sample), "--out", str(out), "--config", str(CI_CONFIG))
    assert done.returncode == 2
    assert "inside the sample" in done.stderr and "a run must not write into what it reads" in done.stderr
    assert len([line for line in done.stderr.splitlines() if line.strip()]) == 1, done.stderr
    assert sha256_tree(sample) == before
