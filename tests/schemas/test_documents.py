"""The stages' JSON documents as models: real documents (a ci run's, in tests/data/documents) read
through their models, written back byte for byte, and fed to every reader, in milliseconds: a
renamed field fails here, before any flow runs. To refresh the documents after a deliberate
change of a model, copy them from a ci run's stage folders (``stages/<stage>/<key>/``; the weld's
sections thinned to a few a line)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from flows.stages.contracts import DocumentError, JsonFile
from flows.stages.outputs import (REFINE_SUMMARY, REGISTRATION_SUMMARY, REPORT, STRESS_SUMMARY, VOLUME_SUMMARY,
                                  WELD_GEOMETRY)
from schemas.stage_documents import Check, FEModelSummary, Report
from schemas.weld_document import SECTION_FIGURES, TOE_FIGURES, WeldGeometry

DOCUMENTS = Path(__file__).resolve().parents[1] / "data" / "documents"
FILES = (WELD_GEOMETRY, VOLUME_SUMMARY, REGISTRATION_SUMMARY, REFINE_SUMMARY, STRESS_SUMMARY, REPORT)


@pytest.mark.parametrize("file", FILES, ids=[f.name for f in FILES])
def test_a_stage_document_reads_into_its_model_and_writes_back_the_same_bytes(file: JsonFile):
    path = DOCUMENTS / file.name
    document = file.read_path(path)
    assert isinstance(document, file.model)
    assert file.dumps(document) == path.read_text()


@pytest.mark.parametrize("where, old, new", [
    ("weld_geometry.json", '"toe_radius_mm": {', '"radius_mm": {'),
    ("weld_geometry.json", '"reinforcement_height_mm": {', '"height_mm": {'),
    ("volume.json", '"tetrahedra":', '"elements":'),
    ("stress.json", '"factor":', '"scf":'),
    ("report.json", '"volume_mesh":', '"fe_model":'),
    ("registration.json", '"common_targets":', '"targets_in_common":'),
])
def test_a_renamed_field_is_refused_where_the_file_is_read_naming_file_and_field(tmp_path, where, old, new):
    file = next(f for f in FILES if f.name == where)
    text = (DOCUMENTS / where).read_text()
    assert old in text
    bad = tmp_path / where
    bad.write_text(text.replace(old, new, 1))
    with pytest.raises(DocumentError) as error:
        file.read_path(bad)
    message = str(error.value)
    assert str(bad) in message and file.model.__name__ in message
    assert old.strip('":{ ') in message or new.strip('":{ ') in message  # the field, missing or unknown


def test_a_document_is_written_only_as_its_model(tmp_path):
    with pytest.raises(TypeError, match="weld_geometry.json: expected a WeldGeometry, got dict"):
        WELD_GEOMETRY.write(tmp_path, {"measured": False})


def test_not_a_number_is_written_as_null_never_as_nan_or_infinity(tmp_path):
    summary = FEModelSummary(made=False, why="x")
    solid = json.loads((DOCUMENTS / "volume.json").read_text())["solid"]
    made = FEModelSummary.model_validate({**json.loads((DOCUMENTS / "volume.json").read_text()),
                                          "solid": {**solid, "volume_mm3": float("inf"),
                                                    "volume_difference": float("nan")}})
    for document in (summary, made):
        VOLUME_SUMMARY.write(tmp_path, document)
        text = (tmp_path / VOLUME_SUMMARY.name).read_text()
        assert "NaN" not in text and "Infinity" not in text
        json.loads(text)  # strict JSON


def test_a_check_is_keyed_pass_in_json_and_pass__in_python():
    check = Check(check="FE model", pass_="all", result="ok", what="one solid")
    assert json.loads(check.model_dump_json(by_alias=True))["pass"] == "all"
    assert Check.model_validate({"check": "c", "pass": "top-L01", "result": "flagged", "what": "w"}).pass_ == "top-L01"
    with pytest.raises(ValueError):
        Check(check="c", pass_="all", result="maybe", what="w")


def test_the_weld_document_names_every_figure_the_acceptance_rules_limit():
    from schemas.acceptance import LIMITED_FIGURES

    assert set(TOE_FIGURES) | set(SECTION_FIGURES) == set(LIMITED_FIGURES)
    geometry = WELD_GEOMETRY.read_path(DOCUMENTS / WELD_GEOMETRY.name)
    section = next(s for s in geometry.sections if s.toes.both())
    for name in SECTION_FIGURES:
        assert section.figure(name) is getattr(section, name)
    toe = section.toes.minus
    assert toe.figure("toe_radius_mm") is toe.toe_radius_mm
    assert toe.figure("groove_depth_mm") is (None if toe.groove is None else toe.groove.depth_mm)


# --- the readers, on the same documents ---

def _geometry() -> WeldGeometry:
    return WELD_GEOMETRY.read_path(DOCUMENTS / WELD_GEOMETRY.name)


def test_the_reports_weld_part_is_the_weld_documents_summary():
    from flows.stages.report import weld_summary

    geometry = _geometry()
    weld = weld_summary(geometry)
    assert weld.measured and weld.verdict == geometry.summary.verdict and weld.sections == geometry.summary.sections
    assert weld.failing_sections == geometry.failing and weld.lines == geometry.lines
    assert weld.acceptance_rule_source == geometry.acceptance.source
    not_measured = weld_summary(WeldGeometry(measured=False, why_not="no weld", joint=None, treatment=None))
    assert not not_measured.measured and not_measured.why_not == "no weld"


def test_the_fe_model_check_reads_the_fe_summary():
    from flows.stages.report import fe_model_check

    made = fe_model_check(VOLUME_SUMMARY.read_path(DOCUMENTS / VOLUME_SUMMARY.name))
    assert made.result == "ok" and "tetrahedra" in made.what and made.measured["min_dihedral_deg"] > 0
    refused = fe_model_check(FEModelSummary(made=False, why="the surface mesh is not closed"))
    assert refused.result == "flagged" and refused.what == "not made: the surface mesh is not closed"
    # an element outside the limits FE programs accept is flagged, naming it (the demo's last one)
    summary = VOLUME_SUMMARY.read_path(DOCUMENTS / VOLUME_SUMMARY.name)
    quality = summary.quality.model_copy(update={
        "below_10_deg": 1, "min_dihedral_deg": summary.quality.min_dihedral_deg.model_copy(update={"worst": 9.0}),
        "aspect_ratio": summary.quality.aspect_ratio.model_copy(update={"worst": 13.2})})
    poor = fe_model_check(summary.model_copy(update={"quality": quality}))
    assert poor.result == "flagged" and "1 element(s) with a smallest dihedral angle under 10 deg (worst 9)" in poor.what
    assert "an aspect ratio of 13.2, over 10" in poor.what


def test_the_published_report_holds_the_stage_documents_unchanged():
    report = REPORT.read_path(DOCUMENTS / REPORT.name)
    assert isinstance(report, Report)
    assert report.volume_mesh == VOLUME_SUMMARY.read_path(DOCUMENTS / VOLUME_SUMMARY.name)
    assert report.registration == REGISTRATION_SUMMARY.read_path(DOCUMENTS / REGISTRATION_SUMMARY.name)
    assert report.refinement == REFINE_SUMMARY.read_path(DOCUMENTS / REFINE_SUMMARY.name)
    from flows.stages.report import stress_summary

    assert report.stress == stress_summary(STRESS_SUMMARY.read_path(DOCUMENTS / STRESS_SUMMARY.name))


def test_the_command_line_summary_reads_the_report(capsys):
    from flows.cli.render import print_run_summary
    from flows.reconstruct import RunResult, TrailHead
    from flows.stages import STAGES

    report = REPORT.read_path(DOCUMENTS / REPORT.name)
    names = [s.name for s in STAGES]
    run = RunResult(report=report, outputs={"report.json": {"path": "/r/results/report.json", "sha256": "0" * 64}},
                    refs={}, cached={n: False for n in names}, seconds={n: 1.0 for n in names},
                    trail_head=TrailHead(seq=7, hash="a" * 64))
    print_run_summary(run, Path("/r"))
    out = capsys.readouterr().out
    assert f"{report.sample_id}: {len(report.passes)} passes" in out
    assert f"weld: {report.weld.sections_measured} of {report.weld.sections} sections measured, " \
           f"{report.weld.verdict}" in out
    assert f"FE model: {report.volume_mesh.solid.tetrahedra:,} tetrahedra" in out
    hot = report.stress.hot_spot
    assert (f"stress: hot spot at the {hot.line} weld's {hot.side} toe, {hot.position_mm:g} mm along it, stress "
            f"concentration {hot.factor:.2f}") in out
    assert f"checks: {len(report.checks)} of {len(report.checks)} ok" in out
    assert "audit trail head: seq 7" in out


def test_the_qa_pages_weld_figures_read_the_weld_document():
    from flows.stages.qa_report import along_weld_pictures
    from tasks.weld_views import chosen_sections

    geometry = _geometry()
    chosen = chosen_sections(geometry, 2)
    assert len(chosen) == 2 * len(geometry.line_names())
    assert all(s in geometry.sections for s in chosen)
    pictures = along_weld_pictures(geometry)
    assert pictures and all(p["src"].startswith("data:image/png;base64,") for p in pictures)


def test_the_report_records_the_runs_settings_as_the_config_model():
    """The QA page draws the weld's sections and the FE model's weld zone with the settings the run
    recorded (report.json), read back through the config model."""
    from schemas.reconstruction import ReconstructionConfig

    report = REPORT.read_path(DOCUMENTS / REPORT.name)
    recorded = ReconstructionConfig.model_validate(report.config)
    assert recorded.model_dump(mode="json") == report.config
    assert recorded.weld.section_step_mm > 0 and recorded.volume.weld_zone_mm >= 0


def test_the_batch_index_reads_the_published_report(tmp_path):
    from data_catalog.catalog import SampleRecord
    from flows.qa_index import _summary

    results = tmp_path / "runs" / "s" / "results"
    results.mkdir(parents=True)
    (results / "report.json").write_text((DOCUMENTS / REPORT.name).read_text())
    report = REPORT.read_path(DOCUMENTS / REPORT.name)
    record = SampleRecord(sample_id="s", sample_dir=str(tmp_path / "s"), fingerprint="f", state="done",
                          failed_stage=None, error=None, out_dir=str(tmp_path / "runs" / "s"), done_fingerprint="f",
                          artefacts={}, flow_run_id=None, registered="2026-11-26T00:00:00+00:00",
                          updated="2026-11-26T00:00:00+00:00")
    row = _summary(record, tmp_path)
    assert row["weld"] == {"verdict": report.weld.verdict, "sections": report.weld.sections,
                           "failing": report.weld.failing or 0}
    assert row["fe"] == report.volume_mesh.solid.tetrahedra
    assert row["checks"] == {"ok": len(report.checks), "total": len(report.checks)}
