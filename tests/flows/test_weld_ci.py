"""Stage ``weld`` on the ci sample, against the simulator's drawn weld (truth/weld_sections.json)."""

from __future__ import annotations

import numpy as np
import pytest

from data_catalog.manifests import load_manifest
from data_catalog.stages import StageStore
from data_catalog.truth import TRUTH_DIR, WELD_TRUTH_NAME, read_weld_truth
from flows.preflight import load_config
from flows.stages import run_in_process
from flows.stages.outputs import REFINED, WELD_GEOMETRY
from simulator.evaluate import T_true_specimen_nominal, summarise_weld_errors, weld_errors
from tests.conftest import CI_CONFIG


@pytest.fixture(scope="module")
def weld_run(ci_sample, tmp_path_factory):
    manifest = load_manifest(ci_sample)
    refs = run_in_process(store=StageStore(tmp_path_factory.mktemp("weld-store")), sample_dir=ci_sample,
                          manifest=manifest, config=load_config(CI_CONFIG), upto="weld")
    geometry = WELD_GEOMETRY.read(refs["weld"])
    T = T_true_specimen_nominal(ci_sample, manifest, REFINED.open(refs["refine"]))
    return refs, geometry, summarise_weld_errors(weld_errors(ci_sample, geometry, T))


def test_ci_weld_figures_against_the_drawn_weld(weld_run):
    """The ci sample is coarse: 0.32 mm between points and profiles, merged into 0.3 mm cells. A
    toe fillet of the ci's 0.3-2 mm radius at 30-60 deg spans r tan(a/2)(1 + cos a) = 0.15-1.3 mm
    across: one to four cells per row, three rows in a 1 mm section, so its radius is only
    roughly determined (median within 0.2 mm, 90 % within 0.4 mm). The flank is read on ~5
    cells of 1.5 mm, each a 0.3 mm average over a surface bending ~6 deg/mm, with sensor noise:
    median within 4 deg, 90 % within 9 deg. The height is a parabola over the peak's cells, the
    bead ripples (0.03-0.12 mm, 1.5-3 mm wavelength along the weld) seen through 0.3 mm cells:
    median within 0.08 mm, worst 0.25 mm. The width is between two toe positions fitted on the
    cells: median within 0.15 mm, worst 0.4 mm. (Measured when written: radius 0.10 / 0.25 mm,
    flank 2.6 / 6.1 deg, height 0.030 / 0.13 mm, width 0.07 / 0.22 mm: median / p90 or worst;
    2026-11-25, the plate line under stickers: radius 0.09 / 0.26, flank 2.5 / 6.1, height
    0.029 / 0.069, width 0.068 / 0.22, undercut worst 0.014 mm.)"""
    refs, geometry, errors = weld_run
    assert geometry.measured and geometry.summary.sections >= 70
    assert geometry.summary.sections_not_measured <= 2
    assert errors["toe_radius_mm"]["median_abs"] <= 0.2 and errors["toe_radius_mm"]["p90_abs"] <= 0.4
    assert errors["flank_angle_deg"]["median_abs"] <= 4.0 and errors["flank_angle_deg"]["p90_abs"] <= 9.0
    assert errors["reinforcement_height_mm"]["median_abs"] <= 0.08
    assert errors["reinforcement_height_mm"]["worst_abs"] <= 0.15  # 0.134 before the plate line's sticker rule
    # a plate line lifted by a sticker read the plate beside the toe as undercut (0.25 mm where none was
    # drawn, confidently). The ci has no undercut drawn: every undercut the fits can pin (1-sigma under
    # 0.1 mm) is under 0.1 mm; one they cannot (a dip in a few noisy plate points: 2026-11-29, top at
    # 11 mm, 0.19 +- 2.45 mm) is never passed: its section is judged uncertain (or failed)
    pinned, loose = [], []
    for sec in geometry.sections:
        for side, toe in sec.toes.sides():
            if toe is not None and toe.undercut_depth_mm.value:
                (pinned if (toe.undercut_depth_mm.sigma or 0.0) <= 0.1 else loose).append((sec, side, toe))
    assert all(toe.undercut_depth_mm.value <= 0.1 for _, _, toe in pinned), pinned
    assert all(sec.verdict in ("uncertain", "fail") and any(f.toe == side and f.figure == "undercut_depth_mm"
                                                           for f in sec.uncertain + sec.violations)
               for sec, side, _ in loose), loose
    assert errors["reinforcement_width_mm"]["median_abs"] <= 0.15
    assert errors["reinforcement_width_mm"]["worst_abs"] <= 0.4
    assert errors["toe_radius_mm"]["n"] >= 140 and errors["reinforcement_height_mm"]["n"] >= 70


def test_ci_misalignment_and_the_weld_line_found(weld_run, ci_sample):
    """The plates' lines are fitted on 14 mm of plate each side (a few hundred cells, stickers
    trimmed): the angular misalignment within 0.1 deg and the axial within 0.1 mm in the median
    (the ci's placement is off by up to 5 mm and 2 deg: the lines are found on the data)."""
    _, geometry, _ = weld_run
    truth = read_weld_truth(ci_sample / TRUTH_DIR / WELD_TRUTH_NAME)
    for line in geometry.lines:
        rows = [s for s in geometry.sections if s.line == line.name]
        sign = 1.0 if line.face_normal[2] > 0 else -1.0  # figures are along the face's outward normal
        angular = np.array([s.angular_misalignment_deg.value for s in rows]) * sign
        axial = np.array([s.axial_misalignment_mm.value for s in rows]) * sign
        assert abs(np.median(angular) - truth.angular_misalignment_deg) <= 0.1, line.name
        assert abs(np.median(axial) - truth.axial_misalignment_mm) <= 0.1, line.name
        assert line.sections >= 35


def test_ci_weld_file_carries_uncertainties_verdicts_and_statistics(weld_run):
    refs, geometry, _ = weld_run
    assert geometry.treatment == "as-welded" and "ISO 5817" in geometry.acceptance.source
    section = next(s for s in geometry.sections if s.passed is not None and s.toes.minus)
    for figure in ("reinforcement_height_mm", "reinforcement_width_mm", "axial_misalignment_mm",
                   "angular_misalignment_deg"):
        assert section.figure(figure).value is not None and section.figure(figure).sigma is not None, figure
    toe = section.toes.minus
    assert toe.toe_radius_mm.sigma is not None and toe.flank_angle_deg.sigma is not None
    stats = geometry.statistics["toe_radius_mm"]
    assert stats.min <= stats.p5 <= stats.median <= stats.p95 <= stats.max
    assert stats.min_at is not None and stats.min_at.toe in ("minus", "plus")
    assert geometry.summary.verdict in ("pass", "fail")
    assert geometry.summary.failing == sum(not s.passed for s in geometry.sections if s.passed is not None)
    # uncertain sections (a figure within its 1-sigma of a limit, or not measured) are said apart
    assert {s.verdict for s in geometry.sections} <= {"pass", "fail", "uncertain", "not measured"}
    assert geometry.summary.sections_uncertain == sum(s.verdict == "uncertain" for s in geometry.sections)
    assert len(geometry.uncertain) == sum(len(s.uncertain) for s in geometry.sections if s.passed)
    assert refs["weld"].metrics["sections"] == geometry.summary.sections
