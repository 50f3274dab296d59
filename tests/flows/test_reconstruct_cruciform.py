"""The ``cruciform`` preset reconstructed by the real flow (ci settings) up to stage ``weld``
(``cruciform_run``: the run stops there, no mesh): its two setups, each with one stem up, matched
on the base plate's walls, and its four fillet welds, two on each face of the base plate, measured
against the drawn ones (``truth/fillet_weld.json``) face by face, within the T-joint's bounds
(tests/flows/test_reconstruct_tjoint.py); then its stress, the base pulled, in a few sections
against the same sections of the drawn cruciform (bench/stress_truth.py)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest

from data_catalog.manifests import load_manifest
from flows.preflight import load_config
from flows.stages.outputs import REFINED, REGISTRATION_SUMMARY, STRESS_SUMMARY, WELD_GEOMETRY
from simulator.evaluate import T_true_specimen_nominal, fillet_errors

from tests.flows.samples import FILLET_CONFIG

os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
REPO = Path(__file__).resolve().parents[2]

UPPER = ("fillet-top-neg", "fillet-top-pos")
LOWER = ("fillet-bottom-neg", "fillet-bottom-pos")


def test_the_setups_meet_at_the_walls(cruciform_run):
    _, report = cruciform_run
    between = REGISTRATION_SUMMARY.read(report["refs"]["registration"]).between_setups
    # measured: 17 targets brought together against a runner-up of 5 (at the preset's seed, 41;
    # at seed 43 the match was 6 against 6: refused as ambiguous, not guessed)
    assert len(between) == 1 and between[0].targets >= 10 and between[0].runner_up < 0.75 * between[0].targets


def test_the_four_fillet_welds_are_measured_on_both_faces_against_the_drawn_ones(cruciform_run, cruciform_sample):
    _, report = cruciform_run
    geometry = WELD_GEOMETRY.read(report["refs"]["weld"])
    assert geometry.measured and geometry.joint == "cruciform fillet"
    assert [line.name for line in geometry.lines] == list(UPPER + LOWER)
    for line in geometry.lines:  # the stem up from the base's face: +z above it, -z below
        assert line.face_normal == (0.0, 0.0, 1.0 if line.name in UPPER else -1.0), line
        assert line.across == (1.0 if line.name.endswith("pos") else -1.0, 0.0, 0.0), line
    assert len(geometry.sections) > 200 and all(sec.toes.both() for sec in geometry.sections)
    T = T_true_specimen_nominal(cruciform_sample, load_manifest(cruciform_sample), REFINED.open(report["refs"]["refine"]))
    for sec in geometry.sections:  # each root, in the true frame, where its stem meets its face (x = +-5, z = +-6 mm)
        x, _, z = T[:3, :3] @ np.asarray(sec.centre_specimen_mm) + T[:3, 3]
        assert abs(abs(x) - 5) < 0.5 and abs(abs(z) - 6) < 0.5 and (z > 0) == (sec.line in UPPER), (x, z, sec.line)
    # The T-joint's bounds, face by face: each setup is the T-joint's stem-up one (the same passes,
    # points 0.32 mm apart, 0.3 mm cells) over fillets drawn by the same model, and the upper two are
    # the T-joint's own (seed 41). Measured (median / p90 / worst |e|, 232 sections a face):
    #   upper: legs 0.065 / 0.30 / 0.49 (base), 0.038 / 0.13 / 0.39 (stem) mm; toe radius 0.042 /
    #   0.14 / 0.63 (base), 0.046 / 0.14 / 0.83 (stem) mm; convexity 0.029 / 0.11; throat 0.040 /
    #   0.14; toe angle past the rounding 2.7 / 7.2 / 12.4 (base), 2.4 / 5.2 / 20.7 (stem) deg
    #   lower: legs 0.049 / 0.19 / 0.46 (base), 0.053 / 0.23 / 0.36 (stem) mm; toe radius 0.049 /
    #   0.12 / 0.21 (base), 0.038 / 0.11 / 0.30 (stem) mm; convexity 0.043 / 0.11; throat 0.040 /
    #   0.12; toe angle past the rounding 2.4 / 6.6 / 13.1 (base), 2.9 / 6.6 / 12.8 (stem) deg
    for lines in (UPPER, LOWER):
        errors = {name: np.abs([e for e, _ in pairs])
                  for name, pairs in fillet_errors(cruciform_sample, geometry, T, lines=lines).items()}
        for name, median, p90 in (("leg_base_mm", 0.12, 0.45), ("leg_stem_mm", 0.12, 0.45),
                                  ("toe_radius_mm (base)", 0.1, 0.3), ("toe_radius_mm (stem)", 0.1, 0.3),
                                  ("convexity_mm", 0.06, 0.2), ("throat_mm", 0.08, 0.25),
                                  ("toe angle against the face past the rounding (base)", 4.0, 10.0),
                                  ("toe angle against the face past the rounding (stem)", 4.0, 10.0)):
            e = errors[name]
            assert len(e) > 100 and np.median(e) < median and np.percentile(e, 90) < p90, \
                (lines, name, np.median(e), np.percentile(e, 90))
        # a leg off by more than a millimetre would be a toe found on the wrong plate or face
        assert max(errors["leg_base_mm"].max(), errors["leg_stem_mm"].max()) < 1.0, lines


def _sparse_config():
    """The run's settings with a section every 40 mm (3 of them; ci.yaml: every 10 mm, 12, three
    minutes for the cruciform's eight toes a section on two cores)."""
    config = load_config(FILLET_CONFIG)
    return config.model_copy(update={"stress": config.stress.model_copy(update={"section_step_mm": 40.0})})


@pytest.fixture(scope="module")
def cruciform_stress(cruciform_run, cruciform_sample):
    """Stage stress on the cruciform's run (its stages up to weld reused), sparse sections. Its refs."""
    from data_catalog.stages import StageStore
    from flows.stages import run_in_process

    out, _ = cruciform_run
    return run_in_process(store=StageStore(out), sample_dir=cruciform_sample, manifest=load_manifest(cruciform_sample),
                          config=_sparse_config(), upto="stress")


def test_the_cruciform_is_pulled_along_its_base_and_its_four_base_toes_carry_the_stress(cruciform_run, cruciform_stress,
                                                                                       cruciform_sample):
    summary = STRESS_SUMMARY.read(cruciform_stress["stress"])
    assert summary.made and "cruciform" in summary.model and len(summary.sections) >= 3
    assert summary.max_imbalance <= 1e-3 and abs(summary.max_membrane_error) <= 0.01
    for section in summary.sections:
        assert {(t.line, t.side) for t in section.toes} == {(line, side) for line in UPPER + LOWER
                                                             for side in ("base", "stem")}
        for toe in section.toes:
            assert 11.5 < toe.plate_thickness_mm < 12.5  # the base plate's 12 mm: its nominal stress
            # the base is pulled; the stems carry next to nothing (measured: 0.0003-0.20)
            assert (1.5 < toe.factor < 4.5) if toe.side == "base" else (0 <= toe.factor < 0.3), toe
    assert summary.hot_spot.side == "base" and abs(summary.convergence.change) < 0.05
    # the drawn cruciform: four straight fillets of the median legs, toes rounded to 1 mm (measured:
    # base toes 2.54-2.57, the drawn T-joint's 2.31: tests/tasks/test_cruciform_section.py)
    drawn = summary.drawn
    assert drawn.made and set(drawn.legs) == set(UPPER + LOWER) and len(drawn.toes) == 8
    assert all((2.3 < t.factor < 2.8) if t.side == "base" else (t.factor < 0.1) for t in drawn.toes), drawn.toes
    sys.path.insert(0, str(REPO / "bench"))
    from stress_truth import compare

    out, _ = cruciform_run
    result = compare(out, cruciform_sample, config=_sparse_config())
    # against the same sections of the drawn cruciform: measured (ci settings, every 10 mm, 48 base
    # toe sections) median 2.8 %, worst 11.0 %, hot spots within 3.0 %; here (every 40 mm, 12) median
    # 2.3 %, worst 9.7 %. Three sections a toe line: its hot spot is one section's figure, held to
    # the sections' worst (measured: -1.3 %, +0.04 %, +7.2 %, +9.7 %), not to the T-joint's 6 %
    # over six (tests/flows/test_reconstruct_tjoint.py)
    assert result["toe_sections"] >= 12 and result["median_difference"] < 0.05 and result["worst_difference"] < 0.16
    for name, toe in result["toes"].items():
        assert abs(toe["difference"]) < 0.13 and toe["apart_mm"] <= 40.0, (name, toe)
    assert set(result["unloaded"]) == {f"{line} stem" for line in UPPER + LOWER}
