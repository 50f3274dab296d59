"""The ``cruciform`` preset reconstructed by the real flow (ci settings) up to stage ``weld``
(``cruciform_run``: the run stops there, no mesh): its two setups, each with one stem up, matched
on the base plate's walls, and its four fillet welds, two on each face of the base plate, measured
against the drawn ones (``truth/fillet_weld.json``) face by face, within the T-joint's bounds
(tests/flows/test_reconstruct_tjoint.py)."""

from __future__ import annotations

import os

import numpy as np

from data_catalog.manifests import load_manifest
from flows.stages.outputs import REFINED, REGISTRATION_SUMMARY, WELD_GEOMETRY
from simulator.evaluate import T_true_specimen_nominal, fillet_errors

os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")

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
    assert len(geometry.sections) > 400 and all(sec.toes.both() for sec in geometry.sections)
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
            assert len(e) > 200 and np.median(e) < median and np.percentile(e, 90) < p90, \
                (lines, name, np.median(e), np.percentile(e, 90))
        # a leg off by more than a millimetre would be a toe found on the wrong plate or face
        assert max(errors["leg_base_mm"].max(), errors["leg_stem_mm"].max()) < 1.0, lines
