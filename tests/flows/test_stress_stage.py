"""Stage ``stress`` on the session's ci run: the stress concentration along every measured toe from
2-D section models, its checks (equilibrium, the plate's membrane stress, the hot spot's
convergence), the published VTU, and the factors against the simulator's true surface through the
same code (bench/stress_truth.py)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import meshio
import numpy as np
import pytest

from flows.stages.outputs import STRESS_SUMMARY

REPO = Path(__file__).resolve().parents[2]


def test_every_toe_gets_its_factor_and_the_checks_hold(ci_run):
    out, report = ci_run
    summary = STRESS_SUMMARY.read(report["refs"]["stress"])
    assert summary.made and len(summary.sections) == 5  # every 10 mm along the ci gauge (deploy/configs/ci.yaml)
    assert summary.max_imbalance <= 1e-3
    assert abs(summary.max_membrane_error) <= 0.01  # measured 0.5 %
    toes = {(t.line, t.side) for s in summary.sections for t in s.toes}
    assert toes == {("top", "minus"), ("top", "plus"), ("bottom", "minus"), ("bottom", "plus")}
    factors = [t.factor for s in summary.sections for t in s.toes]
    assert all(f is not None and 1.2 < f < 4.0 for f in factors), factors  # a toe raises the stress, not tenfold
    # each toe line's hot spot is its highest section, the sample's the highest of those
    for hot in summary.hot_spots:
        rows = [(s.position_mm, t.factor) for s in summary.sections for t in s.toes if (t.line, t.side) == (hot.line, hot.side)]
        assert (hot.position_mm, hot.factor) == max(rows, key=lambda r: r[1])
    assert summary.hot_spot == max(summary.hot_spots, key=lambda h: h.factor)
    c = summary.convergence
    assert (c.line, c.side, c.position_mm) == (summary.hot_spot.line, summary.hot_spot.side, summary.hot_spot.position_mm)
    assert abs(c.change) < 0.05  # measured +1.0 %
    # the peak lies on the part's surface near its toe, in the specimen frame
    for s in summary.sections:
        for t in s.toes:
            assert np.linalg.norm(np.subtract(t.peak_specimen_mm, t.toe_specimen_mm)) <= 1.5 + 1e-6
            assert 19.5 < t.plate_thickness_mm < 20.5  # the ci dog-bone's 20 mm


def test_the_report_and_the_terminal_say_the_hot_spot(ci_run):
    out, report = ci_run
    published = json.loads((out / "results" / "report.json").read_text())
    stress = published["stress"]
    assert stress["made"] and stress["hot_spot"]["factor"] == max(h["factor"] for h in stress["hot_spots"])
    check = next(c for c in published["checks"] if c["check"] == "stress at the toes")
    assert check["result"] == "ok" and f"factor {stress['hot_spot']['factor']:.2f}" in check["what"]


def test_the_section_models_are_published_as_vtu(ci_run):
    out, report = ci_run
    sample_id = json.loads((out / "results" / "report.json").read_text())["sample_id"]
    model = meshio.read(out / "results" / f"{sample_id}_stress.vtu")
    summary = STRESS_SUMMARY.read(report["refs"]["stress"])
    assert len(model.cells_dict["triangle6"]) == sum(s.elements for s in summary.sections)
    principal = model.point_data["max_principal_mpa"]
    assert np.all(np.isfinite(principal))
    # the highest stress in the file is the hot spot's peak, where stress.json puts it
    hot = max((t for s in summary.sections for t in s.toes), key=lambda t: t.peak_mpa)
    k = int(np.argmax(principal))
    assert principal[k] >= hot.peak_mpa - 1e-3 * abs(hot.peak_mpa)
    assert np.linalg.norm(model.points[k] - np.asarray(hot.peak_specimen_mm)) < 1e-3 or principal[k] > hot.peak_mpa


def test_the_factors_against_the_true_surface(ci_run, ci_sample):
    """The same sections of the simulator's true surface through the same code. Measured on the ci
    sample (0.32 mm points, 0.3 mm merge cells; its smallest true toe radii 0.42-0.47 mm, which that
    sampling blunts): 16 toe sections, median difference 5.1 %, worst 14.3 %; the hot spots +3.2,
    -11.2, -14.3 and -7.3 %, in the same section. 2026-11-29, the targets weighed by their rim
    fits and a section meeting the toe lines' end points: 18 toe sections, median 4.4 %, worst
    12.6 %; the hot spots +0.4, -9.9, -12.6 and -4.9 %, one of them 10 mm from the truth's. Far
    from issue 26's 5 % at the hot spot on this coarse preset: the bounds below hold what is
    measured, so that a change for the worse fails."""
    sys.path.insert(0, str(REPO / "bench"))
    from stress_truth import compare

    out, _ = ci_run
    result = compare(out, ci_sample)
    assert result["toe_sections"] >= 16
    assert result["median_difference"] < 0.07
    assert result["worst_difference"] < 0.17
    for name, toe in result["toes"].items():
        assert abs(toe["difference"]) < 0.17 and toe["apart_mm"] <= 10.0, (name, toe)


def test_the_drawn_weld_and_the_resolution_are_reported(ci_run):
    out, report = ci_run
    summary = STRESS_SUMMARY.read(report["refs"]["stress"])
    drawn = summary.drawn
    assert drawn.made and drawn.thickness_mm == 20.0 and set(drawn.caps) == {"top", "bottom"}
    # the caps are the weld stage's median width and height of each line
    from flows.stages.outputs import WELD_GEOMETRY

    geometry = WELD_GEOMETRY.read(report["refs"]["weld"])
    for face, (width, height) in drawn.caps.items():
        rows = [s for s in geometry.sections if s.line == face]
        assert width == pytest.approx(np.median([s.reinforcement_width_mm.value for s in rows]), abs=1e-3)
        assert height == pytest.approx(np.median([s.reinforcement_height_mm.value for s in rows]), abs=1e-3)
    # its four toes, each rounded to 1 mm: a concentration like the measured toes', not a singularity
    assert len(drawn.toes) == 4 and all(1.5 < t.factor < 3.5 for t in drawn.toes), drawn.toes
    # the notch stress is off by default: no notch factors, no fatigue estimate, and the reason said
    assert summary.notch_radius_mm is None and not summary.notch_hot_spots and not summary.fatigue
    assert "notch stress is off" in summary.fatigue_basis
    # the ci sample's points are 0.32 mm apart; its toes (radii 0.4-1.9 mm) are coarser than that
    assert 0.25 < summary.point_spacing_mm < 0.4
    radii = [t.toe_radius_mm for s in summary.sections for t in s.toes]
    assert summary.toes_finer_than_points == sum(r < summary.point_spacing_mm for r in radii)


def test_the_notch_stress_and_the_fatigue_estimate(ci_run, ci_sample, tmp_path):
    """The stage's body again on the ci run's inputs, with the IIW notch stress on and a load range
    in the manifest: every toe gets a notch factor, a toe blunter than the reference radius keeps
    its factor (rounding adds nothing there), a sharper one gets a lower one, and the life is the
    S-N curve's at the notch hot spot."""
    from data_catalog.manifests import load_manifest
    from flows.preflight import load_config
    from flows.stages import stress as stress_stage
    from flows.stages.runner import StageContext
    from schemas.manifest import LoadCase
    from tasks.fatigue import notch_cycles

    out, report = ci_run
    manifest = load_manifest(ci_sample).model_copy(update={"load": LoadCase(nominal_stress_range_mpa=80.0)})
    config = load_config(REPO / "deploy" / "configs" / "ci.yaml")
    settings = config.stress.model_copy(update={"notch_stress": True, "section_step_mm": 20.0})
    ctx = StageContext(out=tmp_path, sample_dir=ci_sample, manifest=manifest, config=config, settings=settings,
                       entry=None, inputs={k: report["refs"][k] for k in ("refine", "segment", "weld")})
    stress_stage.stress(ctx)
    summary = STRESS_SUMMARY.read_path(tmp_path / STRESS_SUMMARY.name)
    assert summary.made and summary.notch_radius_mm == 1.0 and len(summary.sections) == 3
    toes = [t for s in summary.sections for t in s.toes]
    assert all(t.notch_factor is not None and 1.2 < t.notch_factor < 4.0 for t in toes)
    blunt = [t for t in toes if t.toe_radius_mm > 1.2]
    sharp = [t for t in toes if t.toe_radius_mm < 0.7]
    assert blunt and sharp, [t.toe_radius_mm for t in toes]
    for t in blunt:  # nothing to round: the same factor within the meshes' difference
        assert t.notch_factor == pytest.approx(t.factor, rel=0.04), (t.toe_radius_mm, t.factor, t.notch_factor)
    for t in sharp:  # rounded to 1 mm: blunter, a lower stress
        assert t.notch_factor < t.factor, (t.toe_radius_mm, t.factor, t.notch_factor)
    assert len(summary.notch_hot_spots) == 4 and len(summary.fatigue) == 4
    for hot, life in zip(summary.notch_hot_spots, summary.fatigue):
        assert (life.line, life.side, life.notch_factor) == (hot.line, hot.side, hot.factor)
        assert life.notch_range_mpa == pytest.approx(80.0 * hot.factor, abs=1e-3)
        assert life.cycles == pytest.approx(notch_cycles(life.notch_range_mpa, 225.0, 3.0), rel=1e-3)
    assert "FAT 225" in summary.fatigue_basis and "80 MPa" in summary.fatigue_basis
    # against the truth: the true surface's sections rounded the same way (bench/stress_truth.py).
    # Measured on the ci run, every 10 mm: hot spots +4.2, -1.2, +1.8, -0.05 %, median 2.9 %, worst
    # 6.8 % (the plain factors: hot spots to -14 %): rounded to 1 mm, the toes the 0.32 mm points
    # blunt no longer decide the figure
    sys.path.insert(0, str(REPO / "bench"))
    from stress_truth import compare

    result = compare(out, ci_sample, notch=True, stress=tmp_path)
    assert result["toe_sections"] >= 8 and result["median_difference"] < 0.05 and result["worst_difference"] < 0.09
    for name, toe in result["toes"].items():
        assert abs(toe["difference"]) < 0.06, (name, toe)


def _stress_with_a_mesh_spoilt(ci_run, ci_sample, out, monkeypatch, *, meshes_in_call: int | None, index: int):
    """The stress stage's body again on the ci run's inputs into ``out``, one section's mesh spoilt
    (a triangle turned inside out; the one thing stood in for: seen on a provisional section of the
    demo, "nonpositive jacobian"): mesh ``index`` of the ``mesh_sections`` call that makes
    ``meshes_in_call`` meshes (None: as many as the run's sections). Returns the run's stress.json,
    the body's metrics and its stress.json."""
    from data_catalog.manifests import load_manifest
    from flows.preflight import load_config
    from flows.stages import stress as stress_stage
    from flows.stages.runner import StageContext
    from tasks.section_model import SectionMesh

    _, report = ci_run
    before = STRESS_SUMMARY.read(report["refs"]["stress"])
    count = len(before.sections) if meshes_in_call is None else meshes_in_call
    real = stress_stage.mesh_sections

    def spoilt(planes, settings, **kwargs):
        meshes = real(planes, settings, **kwargs)
        if len(meshes) == count:
            flipped = meshes[index].triangles.copy()
            flipped[0] = flipped[0][[0, 2, 1, 5, 4, 3]]
            meshes[index] = SectionMesh(meshes[index].points, flipped)
        return meshes

    monkeypatch.setattr(stress_stage, "mesh_sections", spoilt)
    config = load_config(REPO / "deploy" / "configs" / "ci.yaml")
    ctx = StageContext(out=out, sample_dir=ci_sample, manifest=load_manifest(ci_sample), config=config,
                       settings=config.stress, entry=None,
                       inputs={k: report["refs"][k] for k in ("refine", "segment", "weld")})
    metrics = stress_stage.stress(ctx)
    return before, metrics, STRESS_SUMMARY.read_path(out / STRESS_SUMMARY.name)


def test_a_section_calculix_refuses_is_left_out_and_said(ci_run, ci_sample, tmp_path, monkeypatch):
    """One section's mesh spoilt (``_stress_with_a_mesh_spoilt``; the sections' call, not the hot
    spot's finer one): the real CalculiX refuses it, the other sections are solved as before, the
    refused one is named in stress.json, and the report's stress check is flagged saying where and why."""
    from flows.stages.report import stress_check

    before, metrics, summary = _stress_with_a_mesh_spoilt(ci_run, ci_sample, tmp_path, monkeypatch,
                                                          meshes_in_call=None, index=2)
    assert summary.made and metrics["sections_refused"] == 1
    (refused,) = summary.sections_refused
    assert refused.position_mm == before.sections[2].position_mm and "nonpositive jacobian" in refused.why
    kept = [x for k, x in enumerate(before.sections) if k != 2]
    assert [x.position_mm for x in summary.sections] == [x.position_mm for x in kept]
    for got, want in zip(summary.sections, kept):  # solved alone: the same factors as in one run with the others
        for a, b in zip(got.toes, want.toes):
            assert a.factor == pytest.approx(b.factor, rel=1e-5), (got.position_mm, a, b)
    check = stress_check(summary)
    assert check.result == "flagged" and f"at {refused.position_mm:g} mm" in check.what and "nonpositive" in check.what


def test_a_finer_hot_spot_section_calculix_refuses_leaves_the_stress_and_says_so(ci_run, ci_sample, tmp_path,
                                                                                  monkeypatch):
    """The hot spot's finer section spoilt (``_stress_with_a_mesh_spoilt``; the call that makes one
    mesh): the real CalculiX refuses it; the stress stands as before (every section, the same hot
    spot and factors, the hot section's picture), without a convergence figure, saying why in
    stress.json and the report's stress check (flagged)."""
    from data_catalog.stages import load_arrays
    from flows.stages.outputs import HOT_SECTION
    from flows.stages.report import stress_check

    before, metrics, summary = _stress_with_a_mesh_spoilt(ci_run, ci_sample, tmp_path, monkeypatch,
                                                          meshes_in_call=1, index=0)
    assert before.convergence is not None and before.convergence_refused is None
    assert summary.made and metrics["convergence_refused"] and summary.convergence is None
    assert "nonpositive jacobian" in summary.convergence_refused and "hot spot's section" in summary.convergence_refused
    assert summary.hot_spot == before.hot_spot and summary.sections == before.sections
    assert load_arrays(tmp_path / HOT_SECTION.name, "triangles")["triangles"].shape[0] > 0  # drawn from the section solved
    check = stress_check(summary)
    assert check.result == "flagged" and "convergence not checked" in check.what and "nonpositive" in check.what
    assert check.measured["convergence"] is None


def test_a_missing_solver_is_one_line_at_the_start_and_the_run_goes_on(ci_run, ci_sample, tmp_path):
    """No ``ccx`` on the PATH: one line before any work says so and what installs it; the run goes
    on (here its stages come from the session's stage cache, the stress stage's too)."""
    from tests.flows.cli import weldrecon

    empty = tmp_path / "bin"
    empty.mkdir()
    done = weldrecon("reconstruct", str(ci_sample), "--config", str(REPO / "deploy" / "configs" / "ci.yaml"),
                     "--out", str(tmp_path / "run"), "--stop-after", "stress", env={"PATH": str(empty)})
    assert done.returncode == 0, done.stderr
    first = done.stderr.splitlines()[0]
    assert first.startswith("CalculiX (ccx) is not installed") and "calculix-ccx" in first
    # a run that stops before the stress stage does not need the solver: not a word of it
    done = weldrecon("reconstruct", str(ci_sample), "--config", str(REPO / "deploy" / "configs" / "ci.yaml"),
                     "--out", str(tmp_path / "run2"), "--stop-after", "weld", env={"PATH": str(empty)})
    assert done.returncode == 0 and "CalculiX" not in done.stderr


def test_a_bending_load_bends_the_sections(ci_run, ci_sample, tmp_path):
    """The stage's body again on the ci run's inputs with the manifest's load ``bending``: the
    sections bent about the weld's axis, the top face stretched, no net force; each toe's nominal
    stress the moment over its plate's section modulus (6 M / t^2), the plate's stress through the
    thickness that bending stress (measured within 0.15 %), the top toes a concentration (measured
    1.83-2.25, against 2.06-2.58 pulled: the bending's gradient), the bottom toes, in compression,
    none; the drawn weld bent too (top toes 2.10 against 2.21 pulled), and the model says so."""
    from data_catalog.manifests import load_manifest
    from flows.preflight import load_config
    from flows.stages import stress as stress_stage
    from flows.stages.runner import StageContext
    from schemas.manifest import LoadCase

    out, report = ci_run
    manifest = load_manifest(ci_sample).model_copy(update={"load": LoadCase(kind="bending")})
    config = load_config(REPO / "deploy" / "configs" / "ci.yaml")
    settings = config.stress.model_copy(update={"section_step_mm": 20.0})
    ctx = StageContext(out=tmp_path, sample_dir=ci_sample, manifest=manifest, config=config, settings=settings,
                       entry=None, inputs={k: report["refs"][k] for k in ("refine", "segment", "weld")})
    stress_stage.stress(ctx)
    summary = STRESS_SUMMARY.read_path(tmp_path / STRESS_SUMMARY.name)
    assert summary.made and summary.model == stress_stage.MODEL_BENDING and len(summary.sections) == 3
    assert STRESS_SUMMARY.read(report["refs"]["stress"]).model == stress_stage.MODEL  # no load given: pulled
    assert summary.max_imbalance <= 1e-3 and abs(summary.max_membrane_error) <= 0.01
    for section in summary.sections:
        # one moment through the section: each toe's nominal stress is 6 M / t^2 of it
        moments = [t.nominal_mpa * t.plate_thickness_mm ** 2 / 6 for t in section.toes]
        assert max(moments) == pytest.approx(min(moments), rel=1e-3)
        assert abs(section.force_n_per_mm) < 1e-3 * moments[0] / 20.0  # pure bending: no net force
    top = [t for s in summary.sections for t in s.toes if t.line == "top"]
    bottom = [t for s in summary.sections for t in s.toes if t.line == "bottom"]
    assert top and bottom
    assert all(1.2 < t.factor < 4.0 for t in top), [t.factor for t in top]
    assert all(t.factor < 0.1 for t in bottom), [t.factor for t in bottom]
    assert summary.hot_spot.line == "top" and abs(summary.convergence.change) < 0.05
    assert summary.drawn.made
    for t in summary.drawn.toes:
        assert (1.2 < t.factor < 3.5) if t.line == "top" else t.factor < 0.1, summary.drawn.toes


@pytest.mark.parametrize("model, says", [
    ("2-D sections ...; axial tension across the weld", "its membrane stress off the force over its thickness"),
    ("2-D sections ...; pure bending about the weld's axis", "its bending stress at the surface off 6 M / t^2"),
])
def test_a_failed_plate_check_says_what_it_checked_for_the_load(model, says):
    from flows.stages.report import stress_check
    from schemas.stage_documents import StressSummary

    check = stress_check(StressSummary(made=True, model=model, sections=[], max_imbalance=1e-6,
                                       max_membrane_error=0.05))
    assert check.result == "flagged" and f"the plate's check: {says} by 0.05" in check.what


@pytest.mark.parametrize("at, expected", [
    (12.5, (12.5, 7.0)),  # (y, x) between two toe points: where the line between them crosses
    (10.0 + 1e-15, (10.0, 7.0)),  # on the first point up to rounding, from either side
    (10.0 - 1e-15, (10.0, 7.0)),
    (8.0, (10.0, 7.0)),  # before the first point by less than half the step: it stands for the toe there
    (47.4, (45.0, 7.0)),
    (7.4, None),  # more than half a step past either end: not crossed
    (47.6, None),
])
def test_a_section_meets_a_toe_line_between_its_points_and_half_a_step_past_its_ends(at, expected):
    """Toe points every 5 mm along y (10 ... 45 mm) at x = 7 mm; a section plane across y at ``at``."""
    from flows.stages.stress import _crossing
    from tasks.plate_section import SectionFrame

    y = np.arange(10.0, 46.0, 5.0)
    polyline = np.column_stack([np.full(len(y), 7.0), y, np.zeros(len(y))])
    frame = SectionFrame(origin=np.array([0.0, at, 0.0]), across=np.array([1.0, 0.0, 0.0]),
                         up=np.array([0.0, 0.0, 1.0]), along=np.array([0.0, 1.0, 0.0]))
    hit = _crossing(polyline, frame)
    if expected is None:
        assert hit is None
    else:
        np.testing.assert_allclose(hit[1::-1], expected, atol=1e-12)  # (y, x)
