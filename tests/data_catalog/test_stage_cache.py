"""The stage cache shared by run folders (``$WELDRECON_STAGE_CACHE``): a stage made in one folder
is copied, verified, into another that needs the same key; a damaged cache entry is never copied;
a cache that cannot be written never fails a run."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from data_catalog import audit
from data_catalog.stages import StageStore
from flows.stages.contracts import TextFile
from flows.stages.runner import Stage, run_stage
from schemas.manifest import SampleManifest

NOTE = TextFile("note.txt")
CALLS: list[str] = []


def _body(ctx) -> dict:
    CALLS.append(str(ctx.out))
    NOTE.write_text(ctx.out, f"made for {ctx.manifest.sample_id}\n")
    return {"made": True}


def _view(manifest, entry=None):
    return {"sample_id": manifest.sample_id}


STAGE = Stage("report", False, (), None, (NOTE,), f"{__name__}:_body", f"{__name__}:_view", "a test stage")


@pytest.fixture
def manifest(ci_sample) -> SampleManifest:
    from data_catalog.manifests import load_manifest

    return load_manifest(ci_sample)


def _run(root: Path, cache: Path | None, manifest, ci_sample):
    from schemas.reconstruction import ReconstructionConfig

    return run_stage(STAGE, store=StageStore(root, shared=cache if cache is not None else False), sample_dir=ci_sample,
                     manifest=manifest, config=ReconstructionConfig(), inputs={})


def test_a_stage_made_in_one_folder_is_copied_into_the_next(tmp_path, manifest, ci_sample):
    CALLS.clear()
    cache = tmp_path / "cache"
    first = _run(tmp_path / "a", cache, manifest, ci_sample)
    assert not first.cached and len(CALLS) == 1
    assert (cache / "stages" / "report" / first.key / "note.txt").is_file()  # shared once made
    second = _run(tmp_path / "b", cache, manifest, ci_sample)
    assert second.cached and len(CALLS) == 1 and second.key == first.key
    assert Path(second.path).parent.parent.parent == tmp_path / "b"  # in b's own store, not linked to the cache
    assert Path(second.path, "note.txt").read_bytes() == Path(first.path, "note.txt").read_bytes()
    entry = [e for e in audit.read_trail(tmp_path / "b") if e["kind"] == "stage"][-1]
    assert entry["cached"] is True and entry["from_stage_cache"] == str(cache)
    assert not audit.verify_trail(tmp_path / "b")  # the copy is recorded in b's trail, and intact


def test_a_damaged_cache_entry_is_set_aside_and_the_stage_made_again(tmp_path, manifest, ci_sample):
    CALLS.clear()
    cache = tmp_path / "cache"
    first = _run(tmp_path / "a", cache, manifest, ci_sample)
    (cache / "stages" / "report" / first.key / "note.txt").write_text("edited\n")
    second = _run(tmp_path / "b", cache, manifest, ci_sample)
    assert not second.cached and len(CALLS) == 2
    assert Path(second.path, "note.txt").read_text() == f"made for {manifest.sample_id}\n"
    assert list((cache / "stages" / "report").glob(f".corrupt-{first.key}-*"))


def test_a_cache_that_cannot_be_written_does_not_fail_the_run(tmp_path, manifest, ci_sample):
    cache = tmp_path / "cache"
    cache.write_text("a file where the cache folder should be")
    ref = _run(tmp_path / "a", cache, manifest, ci_sample)
    assert not ref.cached and Path(ref.path, "note.txt").is_file()


def test_without_a_cache_every_folder_makes_its_own(tmp_path, manifest, ci_sample, no_stage_cache):
    CALLS.clear()
    assert StageStore(tmp_path / "x").shared is None  # $WELDRECON_STAGE_CACHE unset
    _run(tmp_path / "a", None, manifest, ci_sample)
    ref = _run(tmp_path / "b", None, manifest, ci_sample)
    assert not ref.cached and len(CALLS) == 2
    assert json.loads(Path(ref.path, "record.json").read_text())["stage"] == "report"


def test_a_commit_that_fails_leaves_no_build_folder(tmp_path, manifest, ci_sample, monkeypatch):
    """A full disk while the record is written: the stage fails, and its build folder is gone at
    once (a long-lived process is alive, so the sweep of dead processes' leftovers would keep it)."""
    import errno

    import data_catalog.stages

    def full(path, text):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(data_catalog.stages, "atomic_write_text", full)
    with pytest.raises(OSError, match="No space left on device"):
        _run(tmp_path / "a", None, manifest, ci_sample)
    assert [p.name for p in (tmp_path / "a" / "stages" / "report").iterdir()] == []
