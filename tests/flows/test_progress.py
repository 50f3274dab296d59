"""The progress display follows a run's audit trail as stages finish (written here from another
thread with the real audit writer), ignores earlier runs' entries and survives a broken line."""

from __future__ import annotations

import io
import json
import threading
import time

from data_catalog import audit
from data_catalog.audit import TRAIL
from flows.progress import TrailProgress


def _stage(run, stage, item=None, *, cached=False, seconds=1.5):
    audit.append(run, "stage", stage=stage, item=item, cached=cached, cache_key="0" * 64,
                 record={"metrics": {"seconds": seconds}})


def test_lines_name_each_stage_and_pass_with_counts_and_times(tmp_path):
    run = tmp_path / "run"
    _stage(run, "denoise", "old-pass")  # an earlier run's entry: not counted
    stream = io.StringIO()

    def writer():
        time.sleep(0.2)
        _stage(run, "denoise", "top-L01", seconds=3.2)
        _stage(run, "denoise", "top-L02", cached=True)
        audit.append(run, "stage-failed", stage="targets", item="top-L02", error="ValueError: no sticker targets")
        with open(run / TRAIL, "a") as handle:  # a broken line, then one more entry (unchained: the display
            handle.write("{not json\n")         # does not verify, the audit does)
            handle.write(json.dumps({"kind": "stage", "stage": "registration", "item": None, "cached": False,
                                     "record": {"metrics": {"seconds": 1.25}}}) + "\n")

    with TrailProgress(run, [("denoise", 2), ("targets", 2), ("registration", 1)], stream=stream, interval_s=0.05):
        thread = threading.Thread(target=writer)
        thread.start()
        thread.join()
    text = stream.getvalue()
    assert "denoise 1/2 top-L01 3.2 s" in text
    assert "denoise 2/2 top-L02 cached" in text
    assert "targets top-L02 FAILED: ValueError: no sticker targets" in text
    assert "registration done 1.2 s" in text or "registration done 1.3 s" in text
    assert "targets 0/2 done, FAILED: top-L02" in text  # the summary names what failed
    assert "old-pass" not in text
    assert all(line.startswith("[") for line in text.splitlines())


def test_a_run_folder_without_a_trail_yet_is_fine(tmp_path):
    stream = io.StringIO()
    with TrailProgress(tmp_path / "new", [("denoise", 1)], stream=stream, interval_s=0.05):
        _stage(tmp_path / "new", "denoise", "p")
    assert "denoise 1/1 p" in stream.getvalue()


def test_entries_of_the_wrong_shape_are_skipped_not_raised(tmp_path):
    run = tmp_path / "run"
    stream = io.StringIO()
    with TrailProgress(run, [("denoise", 2)], stream=stream, interval_s=0.05):
        _stage(run, "denoise", "p1")
        with open(run / TRAIL, "a") as handle:  # valid JSON, wrong shapes
            for bad in ({"kind": "stage", "stage": "denoise", "record": {"metrics": {"seconds": "x"}}},
                        {"kind": "stage", "stage": ["denoise"]}, {"kind": "stage-failed", "stage": "denoise", "item": 7},
                        [1, 2], "text"):
                handle.write(json.dumps(bad) + "\n")
            handle.write(json.dumps({"kind": "stage", "stage": "denoise", "item": "p2", "cached": True}) + "\n")
    text = stream.getvalue()
    assert "denoise 1/2 p1" in text
    assert "denoise 7 FAILED" in text
    assert "denoise 2/2 p2 cached" in text  # the entries of the wrong shape were not counted
