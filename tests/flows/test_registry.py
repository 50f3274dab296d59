"""The stage registry is the one list of stages: well formed, and the docs show it as it is."""

from __future__ import annotations

from pathlib import Path

import pytest

from flows.stages import STAGE_NAMES, STAGES, downstream_of, needed_for, stage, stage_table
from flows.stages.contracts import ArrayFile

REPO = Path(__file__).resolve().parents[2]


def test_names_and_files_are_unique_and_needs_come_first():
    assert len(set(STAGE_NAMES)) == len(STAGE_NAMES)
    files = [o.name for s in STAGES for o in s.outputs]
    assert len(set(files)) == len(files)
    for k, s in enumerate(STAGES):
        assert set(s.needs) <= set(STAGE_NAMES[:k]), s.name
        assert s.settings in (None, "*", s.name)


def test_a_record_names_only_a_registered_stage():
    from pydantic import ValidationError

    from schemas.provenance import STAGE_NAMES as CLOSED, StageRecord

    assert CLOSED == STAGE_NAMES
    with pytest.raises(ValidationError, match="stage"):
        StageRecord.model_validate({"sample_id": "s", "stage": "meshing", "cache_key": "0" * 64, "inputs": {},
                                    "outputs": {}, "parameters": {}, "code_version": "c", "host": "h",
                                    "started": "2026-11-26T00:00:00+00:00", "finished": "2026-11-26T00:00:01+00:00"})


def test_array_outputs_name_their_arrays():
    for s in STAGES:
        for output in s.outputs:
            if isinstance(output, ArrayFile):
                assert output.arrays, f"{s.name}: {output.name} declares no arrays"


def test_downstream_and_lookup():
    assert downstream_of("denoise") == ["refine", "merge", "segment", "weld", "mesh", "export", "volume", "stress",
                                        "report", "qa_report"]
    assert downstream_of("segment") == ["weld", "mesh", "export", "volume", "stress", "report", "qa_report"]
    assert downstream_of("weld") == ["volume", "stress", "report", "qa_report"]
    assert downstream_of("mesh") == ["export", "volume", "report", "qa_report"]
    assert downstream_of("report") == ["qa_report"]
    assert downstream_of("qa_report") == []
    with pytest.raises(KeyError, match="no stage 'surface'"):
        stage("surface")


def test_a_stop_makes_the_stage_and_what_it_needs_only():
    def names(stop):
        return [s.name for s in needed_for(stop)]

    assert names("denoise") == ["denoise"]
    assert names("refine") == ["denoise", "targets", "registration", "refine"]
    assert names("mesh") == ["denoise", "targets", "registration", "refine", "merge", "segment", "mesh"]  # no weld
    assert names("volume") == [n for n in STAGE_NAMES if n not in ("export", "stress", "report", "qa_report")]
    # the stress reads the measured points and toes, not the meshes
    assert names("stress") == ["denoise", "targets", "registration", "refine", "merge", "segment", "weld", "stress"]
    assert names("qa_report") == [n for n in STAGE_NAMES]
    with pytest.raises(KeyError, match="no stage 'meshing'"):
        needed_for("meshing")


def test_the_docs_show_the_registry_as_it_is():
    """docs/reconstruction.md holds ``weldrecon stages``' table as it is (the stage graph on
    docs/architecture.md is checked in tests/test_docs.py)."""
    assert stage_table() in (REPO / "docs" / "reconstruction.md").read_text()
