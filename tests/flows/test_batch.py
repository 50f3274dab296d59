"""The sample catalog and the ``reconstruct_batch`` flow: three ``ci`` samples, one with a
truncated pass file; then the repair; and bad sample folders refused before any work."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest

from data_catalog.audit import read_trail
from data_catalog.catalog import Catalog
from data_catalog.manifests import ManifestError, check_sample_files, load_manifest
from tests.conftest import SIX
from tests.flows.cli import run_cli, weldrecon
from tests.flows.samples import QUICK_CONFIG, copy_sample

REPO = Path(__file__).resolve().parents[2]
CI_CONFIG = str(REPO / "deploy" / "configs" / "ci.yaml")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")


# a subset of the ci sample that reconstructs on its own (both setups, 3 passes each): the batch's
# behaviour, not the reconstruction's accuracy, is what these tests look at


def _copy_sample(ci_sample: Path, dst: Path, sample_id: str, keep: list[str] | None = None) -> Path:
    copy_sample(ci_sample, dst, keep)
    manifest = json.loads((dst / "manifest.json").read_text())
    manifest["sample_id"] = sample_id
    (dst / "manifest.json").write_text(json.dumps(manifest, indent=1))
    return dst


def _largest_chunk(pass_dir: Path) -> Path:
    return max((p for p in (pass_dir / "x_mm").rglob("*") if p.is_file() and p.name != "zarr.json"),
               key=lambda p: p.stat().st_size)


def test_a_failing_sample_does_not_stop_the_batch_and_only_it_reruns_after_repair(ci_sample, tmp_path):
    from flows.batch import reconstruct_batch

    samples = tmp_path / "samples"
    for name in ("a", "b", "c"):
        _copy_sample(ci_sample, samples / name, f"batch-{name}", SIX)
    chunk = _largest_chunk(samples / "c" / "passes" / "bottom-L04.zarr")
    original = chunk.read_bytes()
    chunk.write_bytes(original[: len(original) // 2])  # truncated
    workspace = tmp_path / "ws"

    first = reconstruct_batch(str(workspace), str(samples), QUICK_CONFIG, max_concurrent=2, started_by="pytest")
    assert sorted(first["done"]) == ["batch-a", "batch-b"]
    assert list(first["failed"]) == ["batch-c"]
    why = first["failed"]["batch-c"]
    assert why["stage"] == "denoise" and "bottom-L04" in why["error"]
    catalog = Catalog(workspace)
    # never more than max_concurrent samples at once (Prefect's global concurrency limit): each
    # run's span, from its run-started entry to its last entry
    spans = []
    for record in catalog.list():
        trail = read_trail(Path(record.out_dir))
        spans.append((trail[0]["time"], trail[-1]["time"]))
    assert max(sum(start <= t < end for start, end in spans) for t, _ in spans) <= 2
    states = {r.sample_id: (r.state, r.failed_stage) for r in catalog.list()}
    assert states == {"batch-a": ("done", None), "batch-b": ("done", None), "batch-c": ("failed", "denoise")}
    for sample_id in ("batch-a", "batch-b"):
        record = catalog.get(sample_id)
        stl = Path(record.out_dir) / "results" / f"{sample_id}.stl"
        assert record.artefacts[f"{sample_id}.stl"] and stl.is_file()
        finished = [e for e in read_trail(Path(record.out_dir)) if e["kind"] == "run-finished"]
        assert record.trail_head == {"seq": finished[-1]["seq"], "hash": finished[-1]["hash"]}  # the anchor
    verified = run_cli("audit", "verify", "batch-a", "--workspace", str(workspace))
    assert verified.returncode == 0 and "holds the head kept by the catalog" in verified.stdout
    listed = run_cli("catalog", "list", "--workspace", str(workspace))
    assert "batch-c" in listed.stdout and "failed at denoise" in listed.stdout
    shown = run_cli("catalog", "show", "batch-c", "--workspace", str(workspace))
    assert "bottom-L04" in shown.stdout and "state       failed at stage denoise" in shown.stdout
    # the batch index: every sample, the done ones linked to their QA report (relative links)
    index = Path(first["index"])
    assert index == workspace.resolve() / "index.html"
    page = index.read_text()
    for sample_id in ("batch-a", "batch-b"):
        link = f'href="runs/{sample_id}/results/report.html"'
        assert link in page and (workspace / "runs" / sample_id / "results" / "report.html").is_file()
    assert "batch-c" in page and "failed at denoise" in page and 'href="runs/batch-c' not in page
    assert page.count('alt="mesh of batch-') == 2  # each done sample's mesh picture, inline

    chunk.write_bytes(original)  # repaired
    second = reconstruct_batch(str(workspace), str(samples), QUICK_CONFIG, max_concurrent=2, started_by="pytest")
    assert second["done"] == ["batch-c"] and second["failed"] == {}
    assert sorted(second["up_to_date"]) == ["batch-a", "batch-b"]
    assert catalog.get("batch-c").state == "done"
    assert 'href="runs/batch-c/results/report.html"' in Path(second["index"]).read_text()
    index.unlink()
    rebuilt = weldrecon("catalog", "index", "--workspace", str(workspace))
    assert rebuilt.returncode == 0 and rebuilt.stdout.strip() == f"index: {index}" and index.is_file()
    third = reconstruct_batch(str(workspace), None, QUICK_CONFIG, started_by="pytest")
    assert third["done"] == [] and len(third["up_to_date"]) == 3


def test_catalog_refuses_a_second_folder_with_the_same_sample_id(ci_sample, tmp_path):
    catalog = Catalog(tmp_path / "ws")
    catalog.register(_copy_sample(ci_sample, tmp_path / "one", "dup"))
    with pytest.raises(ValueError, match="already registered"):
        catalog.register(_copy_sample(ci_sample, tmp_path / "two", "dup"))
    with pytest.raises(KeyError, match="nope"):
        catalog.get("nope")
    shown = run_cli("catalog", "show", "nope", "--workspace", str(tmp_path / "ws"))
    assert shown.returncode == 2 and "'nope' is not in the catalog" in shown.stderr


def _edit_manifest(sample: Path, edit) -> None:
    manifest = json.loads((sample / "manifest.json").read_text())
    edit(manifest)
    (sample / "manifest.json").write_text(json.dumps(manifest))


def _first_pass(manifest):
    return manifest["setups"][0]["passes"][0]


@pytest.mark.parametrize("case", ["traversal", "symlink-out", "symlink-dir", "absurd-size", "size-mismatch",
                                  "nan-pose"])
def test_bad_sample_folders_are_refused_before_any_work(ci_sample, tmp_path, case):
    sample = _copy_sample(ci_sample, tmp_path / "s", "bad")
    outside = tmp_path / "elsewhere"
    if case == "traversal":
        _edit_manifest(sample, lambda m: _first_pass(m).update(file="../../etc/passwd"))
        expect = "must not leave the sample folder"
    elif case == "symlink-out":
        first = sample / _first_pass(json.loads((sample / "manifest.json").read_text()))["file"]
        shutil.move(first, outside)
        first.symlink_to(outside)
        expect = "is a symbolic link; expected pass "
    elif case == "symlink-dir":
        shutil.move(sample / "passes", outside)
        (sample / "passes").symlink_to(outside)
        expect = "is a symbolic link; expected pass "
    elif case == "absurd-size":
        _edit_manifest(sample, lambda m: [p.update(n_profiles=9_000_000) for s in m["setups"] for p in s["passes"]])
        expect = "that is not a scan of one specimen"
    elif case == "size-mismatch":
        _edit_manifest(sample, lambda m: _first_pass(m).update(n_profiles=_first_pass(m)["n_profiles"] + 1))
        expect = "the manifest declares n_profiles"
    else:
        _edit_manifest(sample, lambda m: m["scanner"]["T_flange_sensor"][0].__setitem__(3, float("nan")))
        expect = "T_flange_sensor"
    with pytest.raises(ManifestError, match=expect):
        check_sample_files(sample, load_manifest(sample))
    out = tmp_path / "out"
    done = run_cli("reconstruct", str(sample), "--config", CI_CONFIG, "--out", str(out))
    assert done.returncode == 2, done.stdout + done.stderr
    assert expect in done.stderr and "Traceback" not in done.stderr
    assert not out.exists()  # refused before any work
    with pytest.raises(ManifestError, match=expect):
        Catalog(tmp_path / "ws").register(sample)


def test_a_sample_deleted_after_it_was_registered_fails_at_preflight_not_at_none(ci_sample, tmp_path):
    """A sample folder removed mid-batch (after its registration, before its run) was reported
    "FAILED ... at None" (issue 28): it fails at the checks before any stage, and says so."""
    from flows.batch import _reconstruct_one

    sample = _copy_sample(ci_sample, tmp_path / "samples" / "gone", "batch-gone", ["top-L01"])
    workspace = tmp_path / "ws"
    catalog = Catalog(workspace)
    catalog.register(sample)
    record = catalog.get("batch-gone")
    shutil.rmtree(sample)
    outcome = _reconstruct_one(str(workspace), record, CI_CONFIG, "pytest")
    assert outcome["state"] == "failed" and outcome["stage"] == "preflight", outcome
    assert str(sample) in outcome["error"]
    assert Catalog(workspace).get("batch-gone").failed_stage == "preflight"
