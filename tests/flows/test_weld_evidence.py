"""Every weld figure carries its evidence (issue 28): a section is measured only where a weld is
found at the line, a figure the points do not hold is never published, a weld line without a
measured section is a finding, and the verdict and the report's checks say so.

Before: weld lines placed on the plate beside the weld gave "9 of 118 sections measured, fail"
from a sticker's 0.1 mm edge (toes placed to 3e5 mm, 1-sigma; widths 0.6-26 mm); with no rule for
the joint, "None of 82 sections measured" although all were."""

from __future__ import annotations

import math

import numpy as np
import pytest

from data_catalog.manifests import load_manifest
from data_catalog.stages import StageStore
from flows.preflight import load_config
from flows.stages import run_in_process
from flows.stages.outputs import WELD_GEOMETRY
from flows.stages.report import weld_check
from flows.stages.weld import section_settings, verdict_parts
from schemas.reconstruction import WeldGeometryConfig
from tasks.weld_acceptance import judge_weld
from tasks.weld_geometry import MAX_TOE_SIGMA_MM, measure_section
from tests.conftest import CI_CONFIG


def _flat_with_a_sticker(rng, step_mm=0.1):
    """A flat plate section (0.3 mm points, 0.01 mm noise) with a 10 mm wide paper sticker at its middle."""
    u = np.arange(-35.0, 35.0, 0.3)
    u = np.concatenate([u, u])
    s = np.repeat([-0.2, 0.2], len(u) // 2)
    h = rng.normal(0.0, 0.01, len(u)) + np.where(np.abs(u - 2.0) < 5.0, step_mm, 0.0)
    return u, h, s


def test_a_stickers_edge_on_a_plate_is_no_weld():
    rng = np.random.default_rng(3)
    settings = section_settings(WeldGeometryConfig())
    results = [measure_section(*_flat_with_a_sticker(rng), settings=settings, treated=False, line="top",
                               position_mm=float(k), to_frame=lambda a, b: (a, 0.0, b)) for k in range(10)]
    for sec in results:
        assert sec.toes == (None, None) or not math.isfinite(sec.height.value), sec
        assert sec.note, sec  # every section not measured says why
    said = {sec.note.split(":")[0] for sec in results}
    assert said <= {"no weld found at the line here", "no raised weld in the section",
                    "a plate beside the weld has too few points"} | {sec.note for sec in results}, said


def test_the_verdict_counts_measured_sections_without_a_rule_and_names_lines_without_any():
    class Sec:  # what verdict_parts and lines_measured read
        def __init__(self, line):
            self.line = line
    no_rule = verdict_parts(None, [True] * 82, {"top": 41, "bottom": 41})[1]
    assert (no_rule.sections_measured, no_rule.sections_not_measured, no_rule.passed) == (82, 0, None)
    assert no_rule.verdict == "no acceptance rule for this joint and treatment"
    one_line = verdict_parts(None, [True] * 41, {"top": 41, "bottom": 0})[1]
    assert one_line.lines_without_sections == ["bottom"]
    assert one_line.verdict == ("incomplete: weld line bottom without a measured section (not scanned there, or no "
                                "weld found at it)")
    none = verdict_parts(None, [False] * 12, {"top": 0, "bottom": 0})[1]
    assert none.verdict == "not measured: no weld found at the weld lines (bottom, top)"
    assert (none.sections_measured, none.sections_not_measured) == (0, 12)
    assert Sec  # (the class documents the duck type)


@pytest.fixture(scope="module")
def moved_run(ci_sample, tmp_path_factory):
    """The ci sample's weld lines moved 60 mm onto the plate (no weld there, stickers on it)."""
    manifest = load_manifest(ci_sample)
    lines = [line.model_copy(update={"points_mm": [[60.0, p[1], p[2]] for p in line.points_mm]})
             for line in manifest.weld.weld_lines]
    moved = manifest.model_copy(update={"weld": manifest.weld.model_copy(update={"weld_lines": lines})})
    refs = run_in_process(store=StageStore(tmp_path_factory.mktemp("moved-weld")), sample_dir=ci_sample,
                          manifest=moved, config=load_config(CI_CONFIG), upto="weld")
    return WELD_GEOMETRY.read(refs["weld"])


def test_weld_lines_off_the_weld_measure_nothing_and_the_report_flags_it(moved_run):
    geometry = moved_run
    assert geometry.measured and geometry.summary.sections > 50
    assert geometry.summary.sections_measured == 0 and geometry.summary.passed is False
    assert geometry.summary.verdict == "not measured: no weld found at the weld lines (bottom, top)"
    heights = [sec.reinforcement_height_mm.value for sec in geometry.sections]
    assert all(h is None for h in heights)  # no figure without its weld
    toes = [t for sec in geometry.sections for t in (sec.toes.minus, sec.toes.plus) if t is not None]
    assert all(t.position_sigma_mm is not None and t.position_sigma_mm <= MAX_TOE_SIGMA_MM for t in toes)
    check = weld_check(geometry)  # the report's check (flows.stages.report), on the terminal as a warning line
    assert check.check == "weld measured" and check.result == "flagged" and check.what == geometry.summary.verdict


def test_the_weld_check_is_ok_only_for_a_judged_weld_at_every_line(moved_run):
    geometry = moved_run
    judged = geometry.model_copy(update={"summary": verdict_parts(judge_weld([], geometry.acceptance), [True] * 4,
                                                                  {"top": 2, "bottom": 2})[1]})
    assert weld_check(judged).result == "ok"
    unjudged = judged.model_copy(update={"acceptance": None})
    assert weld_check(unjudged).result == "flagged" and "not judged" in weld_check(unjudged).what
