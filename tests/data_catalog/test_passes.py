"""The pass store: written block by block, read back exactly, and refused when broken."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import zarr

from data_catalog.passes import PassFormatError, PassWriter, read_pass


def _write(path, n=10, m=6, chunk=4, complete=True):
    rng = np.random.default_rng(0)
    x = rng.normal(size=(n, m)).astype(np.float32)
    z = (200 + rng.normal(size=(n, m))).astype(np.float32)
    x[0, 0] = z[0, 0] = np.nan
    intensity = rng.integers(1, 1024, size=(n, m)).astype(np.uint16)
    poses = np.repeat(np.eye(4)[None], n, 0)
    writer = PassWriter(path, pass_id="p1", n_profiles=n, n_columns=m, chunk_profiles=chunk, with_poses=True)
    for start in range(0, n, chunk):
        s = slice(start, min(start + chunk, n))
        writer.write(start, x_mm=x[s], z_mm=z[s], intensity=intensity[s], timestamp_s=np.arange(n)[s] * 0.1,
                     T_world_flange=poses[s])
    if complete:
        writer.close()
    return x, z, intensity


def test_round_trip(tmp_path):
    x, z, intensity = _write(tmp_path / "p1.zarr")
    data = read_pass(tmp_path / "p1.zarr", pass_id="p1")
    np.testing.assert_array_equal(data.x_mm, x)
    np.testing.assert_array_equal(data.z_mm, z)
    np.testing.assert_array_equal(data.intensity, intensity)
    assert data.T_world_flange.shape == (10, 4, 4)
    part = read_pass(tmp_path / "p1.zarr", profiles=slice(4, 8))
    np.testing.assert_array_equal(part.z_mm, z[4:8])


def test_missing_file_names_the_pass(tmp_path):
    with pytest.raises(PassFormatError, match=r"pass top-L01: pass file .*nope.zarr does not exist"):
        read_pass(tmp_path / "nope.zarr", pass_id="top-L01")


def test_truncated_store_is_refused(tmp_path):
    _write(tmp_path / "p1.zarr")
    chunk_file = next(p for p in (tmp_path / "p1.zarr" / "z_mm").rglob("*") if p.is_file() and p.name != "zarr.json")
    chunk_file.unlink()
    with pytest.raises(PassFormatError, match=r"pass p1 .*'z_mm' has 2 of 3 chunks on disk; the file is truncated"):
        read_pass(tmp_path / "p1.zarr", pass_id="p1")


def test_truncated_chunk_bytes_are_refused(tmp_path):
    _write(tmp_path / "p1.zarr")
    chunk_file = sorted(p for p in (tmp_path / "p1.zarr" / "z_mm").rglob("*") if p.is_file() and p.name != "zarr.json")[0]
    chunk_file.write_bytes(chunk_file.read_bytes()[:7])
    with pytest.raises(PassFormatError, match=r"pass p1: .*z_mm cannot be decoded .*corrupt"):
        read_pass(tmp_path / "p1.zarr", pass_id="p1")


def test_unfinished_store_is_refused(tmp_path):
    _write(tmp_path / "p1.zarr", complete=False)
    with pytest.raises(PassFormatError, match="was not completely written"):
        read_pass(tmp_path / "p1.zarr")


def test_other_formats_are_refused(tmp_path):
    group = zarr.open_group(str(tmp_path / "other.zarr"), mode="w")
    group.attrs["format"] = "something-else"
    with pytest.raises(PassFormatError, match="has format 'something-else'"):
        read_pass(tmp_path / "other.zarr")
    (tmp_path / "plain").mkdir()
    with pytest.raises(PassFormatError, match="is not a zarr v3 group"):
        read_pass(tmp_path / "plain")


def test_wrong_pass_id_is_refused(tmp_path):
    _write(tmp_path / "p1.zarr")
    shutil.copytree(tmp_path / "p1.zarr", tmp_path / "p2.zarr")
    with pytest.raises(PassFormatError, match="holds pass 'p1', not 'p2'"):
        read_pass(tmp_path / "p2.zarr", pass_id="p2")


def test_blocks_must_come_in_order(tmp_path):
    writer = PassWriter(tmp_path / "p.zarr", pass_id="p", n_profiles=4, n_columns=2, chunk_profiles=2, with_poses=False)
    block = np.zeros((2, 2))
    with pytest.raises(ValueError, match="expected start 0, got 2"):
        writer.write(2, x_mm=block, z_mm=block, intensity=block, timestamp_s=np.zeros(2))


def test_a_pass_is_complete_only_once_its_writer_closed_it(tmp_path):
    from data_catalog.passes import pass_is_complete

    path = tmp_path / "p1.zarr"
    assert not pass_is_complete(path)  # absent
    _write(path, complete=False)
    assert not pass_is_complete(path)  # every block written, not closed
    shutil.rmtree(path)
    _write(path)
    assert pass_is_complete(path)
    (path / "zarr.json").write_text("{not json")
    assert not pass_is_complete(path)  # unreadable: not complete, no error


def test_a_store_in_other_units_is_refused(tmp_path):
    _write(tmp_path / "p1.zarr")
    group = zarr.open_group(str(tmp_path / "p1.zarr"), mode="r+")
    group.attrs["units"] = "inch"
    with pytest.raises(PassFormatError, match="has units 'inch', expected 'mm'"):
        read_pass(tmp_path / "p1.zarr")


def test_a_stage_folder_without_its_record_is_set_aside_when_the_stage_commits(tmp_path):
    """A committed stage folder whose record.json went (deleted by hand) must not be kept as if an
    identical run had finished first: the rerun's commit sets it aside and puts its own in place."""
    from data_catalog.stages import RECORD_NAME, StageRecord, StageStore

    store = StageStore(tmp_path)
    final = store.path("merge", "a" * 64)
    final.mkdir(parents=True)
    (final / "merged.zarr").write_text("left without a record")
    build = store.build_dir("merge")
    (build / "merged.zarr").write_text("fresh")
    record = StageRecord(sample_id="s", stage="merge", item=None, cache_key="a" * 64, inputs={},
                         outputs={"merged.zarr": ""}, parameters={}, code_version="c", host="h",
                         started="2026-11-23T00:00:00Z", finished="2026-11-23T00:00:01Z", metrics={})
    store.commit(build, record)
    assert (final / RECORD_NAME).is_file() and (final / "merged.zarr").read_text() == "fresh"
    assert store.lookup("merge", "a" * 64) is not None
    aside = list(final.parent.glob(".incomplete-*"))
    assert len(aside) == 1 and (aside[0] / "merged.zarr").read_text() == "left without a record"
