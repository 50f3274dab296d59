"""The section fits recover the drawn weld: the simulator's own cap (power-law flank, toe fillet,
undercut, HFMI groove) sampled as a profile at the paper's 0.02 mm, with and without sensor noise;
an under-treated groove fails its limits, located; bad settings and limits are refused by field."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from pydantic import ValidationError

from data_catalog.acceptance import load_acceptance_limits
from flows.preflight import load_config
from flows.stages.weld import section_settings
from schemas.reconstruction import WeldGeometryConfig
from schemas.simulation import WeldConfig
from simulator.weld import draw_weld_cap
from tasks.weld_acceptance import judge_weld
from tasks.weld_fits import Measured, fit_groove, fit_plate_line
from tasks.weld_geometry import along_weld_statistics, measure_section, measure_weld_line

DEFAULTS = WeldGeometryConfig()
SETTINGS = section_settings(DEFAULTS)  # as stage weld reads its sections


def _cap(*, height=2.0, width=16.0, flank=30.0, radius=1.0, undercut=0.0, groove=None):
    """A cap with constant figures along the weld (every range a point), no ripple, no wander."""
    kw = dict(cap_height_mm=(height, height), cap_width_mm=(width, width), flank_angle_deg=(flank, flank),
              toe_radius_mm=(radius, radius), ripple_amplitude_mm=(0.0, 0.0), bead_wander_mm=0.0,
              undercut_depth_mm=(undercut, undercut), undercut_probability=1.0 if undercut else 0.0)
    if groove is not None:
        kw.update(treatment="hfmi-treated", hfmi_groove_width_mm=(groove[0], groove[0]),
                  hfmi_groove_depth_mm=(groove[1], groove[1]))
    return draw_weld_cap(WeldConfig(**kw), np.random.default_rng(0), centre_x_mm=0.0, y_extent_mm=50.0)


def _profile(cap, *, spacing=0.02, noise=0.0, seed=1):
    """Three rows of points across the weld, jittered along it, heights with Gaussian noise."""
    rng = np.random.default_rng(seed)
    u = np.concatenate([np.arange(-30, 30, spacing) + rng.uniform(0, spacing) for _ in range(3)])
    h = cap.height_mm(u, np.zeros_like(u))[0] + noise * rng.standard_normal(len(u))
    return u, h


def _section(cap, *, treated=False, **kw):
    u, h = _profile(cap, **kw)
    return measure_section(u, h, np.zeros_like(u), settings=SETTINGS, treated=treated, line="top", position_mm=12.0,
                           to_frame=lambda a, b: (a, 12.0, b))


@pytest.mark.parametrize("noise", [0.0, 0.005])
@pytest.mark.parametrize(("flank", "radius"), [(30.0, 1.0), (45.0, 0.5), (20.0, 2.0)])
def test_as_welded_toe_radius_flank_angle_height_and_width(noise, flank, radius):
    """Noise-free, what is left is the model's: the fit's flank bends as a parabola, the drawn one
    as a power law (at 45 deg on a 2 x 16 mm cap that leaves ~0.8 deg). With 5 um noise (the
    paper's sensor, ~4 um range resolution) at 0.02 mm spacing: the issue's goal, radius
    +-0.05 mm, angle +-1 deg, height +-0.02 mm."""
    section = _section(_cap(flank=flank, radius=radius), noise=noise)
    tol_r, tol_a, tol_h = (0.02, 1.0, 0.01) if noise == 0 else (0.05, 1.0, 0.02)
    for toe in section.toes:
        assert toe is not None and toe.groove is None
        assert abs(toe.notch_radius.value - radius) <= tol_r, (toe.side, toe.notch_radius)
        assert abs(toe.flank_angle_deg.value - flank) <= tol_a, (toe.side, toe.flank_angle_deg)
        assert np.isfinite(toe.notch_radius.sigma) and np.isfinite(toe.flank_angle_deg.sigma)
    assert abs(section.height.value - 2.0) <= tol_h
    assert abs(section.width.value - 16.0) <= 0.05
    assert abs(section.axial_misalignment.value) < 0.005 and abs(section.angular_misalignment_deg.value) < 0.05
    if noise:
        assert 0 < section.height.sigma < 0.02


def test_undercut_depth():
    section = _section(_cap(undercut=0.2), noise=0.005)
    for toe in section.toes:
        assert abs(toe.undercut_depth.value - 0.2) <= 0.02, toe.undercut_depth


@pytest.mark.parametrize("spacing", [0.02, 0.1])
def test_hfmi_groove_depth_width_radius_and_toe_within(spacing):
    width, depth = 4.0, 0.4
    section = _section(_cap(groove=(width, depth)), treated=True, spacing=spacing, noise=0.005)
    radius = (width ** 2 / 4 + depth ** 2) / (2 * depth)
    for toe in section.toes:
        g = toe.groove
        assert g is not None
        assert abs(g.depth.value - depth) <= 0.02 and g.depth.sigma < 0.02
        assert abs(g.width.value - width) <= 0.1
        assert abs(g.radius.value - radius) <= 0.2
        assert g.toe_within
        assert toe.notch_radius.value == g.radius.value  # a treated toe's radius is its groove's
    assert abs(section.height.value - 2.0) <= 0.02


def test_an_under_treated_groove_fails_located():
    """A groove of 0.1 mm (the IIW figure quoted in the defaults asks for 0.2 mm at least) fails
    on both toes of its section, named by line, toe and position; the weld fails with it."""
    rule = load_acceptance_limits(None).rule_for("double-sided butt", "hfmi-treated")
    good = _section(_cap(groove=(4.0, 0.4)), treated=True, noise=0.005)
    shallow = _section(_cap(groove=(4.0, 0.1)), treated=True, noise=0.005)
    shallow = type(shallow)(**{**shallow.__dict__, "position_mm": 13.0})
    verdict = judge_weld([good, shallow], rule)
    assert verdict.sections[0].passed, verdict.sections[0].violations
    assert not verdict.sections[1].passed and not verdict.passed
    assert verdict.n_failing == 1 and verdict.n_measured == 2
    depth = [v for v in verdict.sections[1].violations if v.figure == "groove_depth_mm"]
    assert {(v.line, v.position_mm, v.toe, v.limit) for v in depth} == {("top", 13.0, "minus", ">= 0.2"),
                                                                          ("top", 13.0, "plus", ">= 0.2")}
    assert all(abs(v.value - 0.1) < 0.02 for v in depth)


def test_plate_line_ignores_a_sticker_on_a_third_of_its_window():
    rng = np.random.default_rng(3)
    u = rng.uniform(16, 30, 600)
    h = 10.0 + 0.01 * u + 0.003 * rng.standard_normal(600)
    h[(u > 20) & (u < 25)] += 0.1  # a 5 mm paper sticker, 0.1 mm thick
    fit = fit_plate_line(u, h, min_points=8)
    assert abs(fit.slope - 0.01) < 0.001 and abs(fit.intercept - 10.0) < 0.02
    with pytest.raises(ValueError, match="u and h must be"):
        fit_plate_line(u, h[:-1], min_points=8)


def test_a_weld_line_in_3d_refined_on_the_data():
    """The cap on a plate's top face, the manifest's line 1.5 mm off the real weld and turned by
    1 degree: the sections find the weld and the refined line its offset."""
    cap = _cap(flank=35.0, radius=1.0)
    rng = np.random.default_rng(5)
    x = rng.uniform(-32, 32, 120_000)
    y = rng.uniform(-20, 20, 120_000)
    z = 10.0 + cap.height_mm(x, y)[0]
    points = np.stack([x, y, z], 1)
    normals = np.tile([0.0, 0.0, 1.0], (len(x), 1))
    turn = np.radians(1.0)
    line = np.array([[1.5 - 20 * np.sin(turn), -20.0, 10.0], [1.5 + 20 * np.sin(turn), 20.0, 10.0]])
    found = measure_weld_line(points, normals, line, name="top", step_mm=2.0, section_half_width_mm=0.5,
                              reach_mm=32.0, end_margin_mm=2.0, min_normal_cos=0.2, settings=SETTINGS, treated=False)
    assert len(found.sections) >= 15
    assert abs(found.offset_mm + 1.5) < 0.1 and abs(found.turn_deg + 1.0) < 0.2
    heights = np.array([s.height.value for s in found.sections])
    assert np.all(np.abs(heights - 2.0) < 0.05)
    flank = np.array([t.flank_angle_deg.value for s in found.sections for t in s.toes])
    assert np.median(np.abs(flank - 35.0)) < 2.0
    stats = along_weld_statistics(heights, [s.position_mm for s in found.sections])
    assert stats["n"] == len(heights) and stats["min"] <= stats["median"] <= stats["max"]
    assert stats["max_at"] in [s.position_mm for s in found.sections]
    with pytest.raises(ValueError, match="points and normals"):
        measure_weld_line(points, normals[:-1], line, name="top", step_mm=2.0, section_half_width_mm=0.5,
                          reach_mm=32.0, end_margin_mm=2.0, min_normal_cos=0.2, settings=SETTINGS, treated=False)
    # sections measured on three threads: the same measurement, section for section
    threaded = measure_weld_line(points, normals, line, name="top", step_mm=2.0, section_half_width_mm=0.5,
                                 reach_mm=32.0, end_margin_mm=2.0, min_normal_cos=0.2, settings=SETTINGS,
                                 treated=False, workers=3)
    assert threaded == found


@pytest.mark.parametrize("face", [1.0, -1.0])
def test_a_plate_thinner_than_the_reach_keeps_its_face_normal(face):
    """Both faces of a 20 mm plate lie within a 32 mm reach of a line on one of them, their normals
    as many one way as the other (the paper preset: their mean, ~0.005 long, was read as a face
    tilted 26 deg): the face is still the one the line is on, its normal straight out of it."""
    cap = _cap(flank=35.0, radius=1.0)
    rng = np.random.default_rng(6)
    n = 240_000
    near_face = np.arange(n) < n // 2  # half the points on the line's face, half on the far one
    # (the far face where it is within reach of the line: |x| < 24 mm, 20 mm below it)
    x, y = np.where(near_face, rng.uniform(-32, 32, n), rng.uniform(-24, 24, n)), rng.uniform(-20, 20, n)
    bump = cap.height_mm(x, y)[0]
    z = np.where(near_face, face * (10.0 + bump), -face * 10.0)
    sign = np.where(near_face, face, -face)
    # the cap's normals tilt across the weld; the plate's are straight; a little noise on all
    normals = np.stack([np.zeros(n), np.zeros(n), sign], 1) + rng.normal(0.0, 0.05, (n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    line = np.array([[0.0, -20.0, face * 10.0], [0.0, 20.0, face * 10.0]])
    found = measure_weld_line(np.stack([x, y, z], 1), normals, line, name="top", step_mm=2.0, section_half_width_mm=0.5,
                              reach_mm=32.0, end_margin_mm=2.0, min_normal_cos=0.2, settings=SETTINGS, treated=False)
    assert np.degrees(np.arccos(np.clip(found.normal[2] * face, -1, 1))) < 0.5, found.normal
    assert len(found.sections) >= 15
    heights = np.array([s.height.value for s in found.sections])
    assert np.all(np.abs(heights - 2.0) < 0.05)


def test_bad_weld_settings_are_refused_with_the_field_named(tmp_path):
    with pytest.raises(ValidationError, match="plate_window_mm"):
        WeldGeometryConfig(plate_window_mm=(20.0, 10.0))
    config = tmp_path / "bad.yaml"
    config.write_text("weld:\n  section_step_mm: 0\n")
    with pytest.raises(ValueError, match=r"weld\.section_step_mm: Input should be greater than 0"):
        load_config(config)
    config.write_text("weld:\n  acceptance:\n    rules:\n      - {joint: double-sided butt, treatment: hfmi-treated,"
                      " source: x, groove_depth_mm: {min: 0.6, max: 0.2}}\n")
    with pytest.raises(ValueError, match=r"weld\.acceptance\.rules\.0\.groove_depth_mm: Value error, min 0.6 is above max 0.2"):
        load_config(config)


def test_bad_acceptance_limits_are_refused_with_the_field_named(tmp_path):
    limits = tmp_path / "limits.yaml"
    limits.write_text("rules:\n  - {joint: double-sided butt, treatment: hfmi-treated, source: x,"
                      " groove_depth_mm: {min: -0.2}}\n")
    with pytest.raises(ValueError, match=r"limits.yaml: invalid weld acceptance limits:\n  rules\.0\.groove_depth_mm\.min: "
                                         r"Input should be greater than or equal to 0"):
        load_acceptance_limits(limits)
    limits.write_text("rules:\n  - {joint: double-sided butt, treatment: hfmi, source: x}\n")
    with pytest.raises(ValueError, match=r"rules\.0\.treatment: Input should be"):
        load_acceptance_limits(limits)
    limits.write_text("rules:\n  - {joint: j, treatment: as-welded, source: x}\n  - {joint: j, treatment: as-welded, source: y}\n")
    with pytest.raises(ValueError, match=r"rules: Value error, one rule per joint and treatment"):
        load_acceptance_limits(limits)


def test_the_default_limits_name_their_source():
    limits = load_acceptance_limits(None)
    rule = limits.rule_for("double-sided butt", "hfmi-treated")
    assert rule.groove_depth_mm.min == 0.2 and rule.toe_within_groove and "Marquis & Barsoum 2016" in rule.source
    assert limits.rule_for("double-sided butt", "as-welded") is not None


def _with_groove_depth(section, depth: Measured, *, position_mm: float):
    """The section with its minus toe's groove depth replaced (the fits' output, as the judge sees it)."""
    minus, plus = section.toes
    groove = dataclasses.replace(minus.groove, depth=depth)
    return dataclasses.replace(section, toes=(dataclasses.replace(minus, groove=groove), plus), position_mm=position_mm)


def test_a_figure_within_its_sigma_of_a_limit_is_uncertain_not_failed():
    """Groove depth limit 0.6 mm: 0.61 +- 0.02 and 0.59 +- 0.02 straddle it (uncertain: listed,
    the section neither passed nor failed silently), 0.65 +- 0.02 breaks it for certain, 0.61
    without a sigma breaks it on its value; with uncertain_sigmas 0 the value alone decides."""
    rule = load_acceptance_limits(None).rule_for("double-sided butt", "hfmi-treated")
    assert rule.uncertain_sigmas == 1.0
    good = _section(_cap(groove=(4.0, 0.4)), treated=True, noise=0.005)
    cases = [(Measured(0.61, 0.02), "uncertain"), (Measured(0.59, 0.02), "uncertain"), (Measured(0.65, 0.02), "fail"),
             (Measured(0.61, float("nan")), "fail"), (Measured(0.55, 0.02), "pass")]
    sections = [_with_groove_depth(good, d, position_mm=10.0 + k) for k, (d, _) in enumerate(cases)]
    verdict = judge_weld(sections, rule)
    assert [s.verdict for s in verdict.sections] == [want for _, want in cases]
    assert [s.passed for s in verdict.sections] == [True, True, False, False, True]
    unsure = verdict.sections[0].uncertain
    assert [(u.toe, u.figure, u.limit, u.value, u.sigma) for u in unsure] == [("minus", "groove_depth_mm", "<= 0.6", 0.61, 0.02)]
    assert verdict.n_failing == 2 and verdict.n_uncertain == 2 and not verdict.passed
    assert judge_weld(sections[:2], rule).passed  # uncertain sections alone do not fail the weld
    strict = judge_weld(sections, rule.model_copy(update={"uncertain_sigmas": 0.0}))
    assert [s.verdict for s in strict.sections] == ["fail", "pass", "fail", "fail", "pass"]


def _grooved_profile(*, width, depth, centre_from_toe, spacing=0.02, noise=0.005, seed=2):
    """An as-welded 2 x 16 mm cap (30 deg, r 1 mm) with a circular groove of ``width`` x ``depth``
    cut beside each toe, its centre ``centre_from_toe`` mm outward of the drawn toe (the
    simulator puts it at a quarter of its width: the toe inside the groove)."""
    u, h = _profile(_cap(), spacing=spacing, noise=0.0, seed=seed)
    radius = (width ** 2 / 4 + depth ** 2) / (2 * depth)
    du = np.abs(u) - (8.0 + centre_from_toe)
    groove = np.where(np.abs(du) < radius, -depth + radius - np.sqrt(np.maximum(radius ** 2 - du ** 2, 0.0)), np.inf)
    return u, np.minimum(h, groove) + noise * np.random.default_rng(seed).standard_normal(len(u))


@pytest.mark.parametrize("spacing", [0.02, 0.25])
def test_a_wide_shallow_groove_keeps_its_toe_within_and_a_groove_beside_the_toe_does_not(spacing):
    """A 5.6 x 0.21 mm groove (radius 18.8 mm) cut over the toe: its wall crosses the plate's
    level at 0.15 mm per mm, a millimetre of it within 0.05 mm of the plate, yet it is groove,
    not plate left between groove and weld (on its circle): the toe is within. The same groove
    cut 1.5 mm beyond the toe leaves 1.5 mm of plate and the original toe: not within, and the
    section fails the rule for it."""
    rule = load_acceptance_limits(None).rule_for("double-sided butt", "hfmi-treated")
    for centre, within in ((0.25 * 5.6, True), (1.5 + 2.8, False)):
        u, h = _grooved_profile(width=5.6, depth=0.21, centre_from_toe=centre, spacing=spacing)
        section = measure_section(u, h, np.zeros_like(u), settings=SETTINGS, treated=True, line="top",
                                  position_mm=12.0, to_frame=lambda a, b: (a, 12.0, b))
        for toe in section.toes:
            assert toe.groove is not None and toe.groove.toe_within is within, (centre, toe.side)
            assert abs(toe.groove.depth.value - 0.21) < 0.02 and abs(toe.groove.width.value - 5.6) < 0.3
        figures = {v.figure for v in judge_weld([section], rule).sections[0].violations}
        assert ("toe_within_groove" in figures) is not within


def test_a_groove_seen_on_one_side_of_its_bottom_has_its_width_not_measured_and_is_uncertain():
    """The groove's inner wall unseen (the points between the weld and the groove's bottom gone,
    as in a shadow): its circle holds on one wall only, its radius and width are extrapolations,
    so they are not measured (NaN, the reason in the note) rather than reported; the depth is
    still read, and the judge lists the width as uncertain ("not measured"), not passed."""
    rule = load_acceptance_limits(None).rule_for("double-sided butt", "hfmi-treated")
    u, h = _grooved_profile(width=4.0, depth=0.4, centre_from_toe=1.0, spacing=0.1)
    gone = (np.abs(u) > 8.0 - 1.0) & (np.abs(u) < 8.0 + 1.0 - 0.05)
    section = measure_section(u[~gone], h[~gone], np.zeros(int((~gone).sum())), settings=SETTINGS, treated=True,
                              line="top", position_mm=12.0, to_frame=lambda a, b: (a, 12.0, b))
    for toe in section.toes:
        g = toe.groove
        assert g is not None and not np.isfinite(g.width.value) and not np.isfinite(g.radius.value)
        assert "not measured" in toe.note and abs(g.depth.value - 0.4) < 0.03
    verdict = judge_weld([section], rule).sections[0]
    assert verdict.verdict == "uncertain" and verdict.passed
    assert {(v.toe, v.figure, v.limit) for v in verdict.uncertain} == {("minus", "groove_width_mm", "not measured"),
                                                                      ("plus", "groove_width_mm", "not measured")}


def test_a_stray_return_below_the_groove_is_not_its_bottom():
    """One point 2 mm below a 0.3 mm groove (a stray return the merge kept): the groove is still
    found, its bottom where the profile's running median is deepest, its circle fitted without
    the stray point (old: the stray point alone deeper than a quarter of its depth: no groove)."""
    u, h = _grooved_profile(width=4.0, depth=0.3, centre_from_toe=1.0, spacing=0.1)
    for sign in (-1, 1):
        k = int(np.argmin(np.abs(u - sign * 9.3)))
        h[k] -= 2.0
    section = measure_section(u, h, np.zeros_like(u), settings=SETTINGS, treated=True, line="top", position_mm=12.0,
                              to_frame=lambda a, b: (a, 12.0, b))
    for toe in section.toes:
        g = toe.groove
        assert g is not None and abs(g.depth.value - 0.3) < 0.02 and abs(g.width.value - 4.0) < 0.2, toe


# one toe of the demo sample (bottom line, 13 mm; its plus side, plate-relative): the groove's inner
# wall meets a steep flank that the scanner saw in clumps of points 0.4 mm apart, v from the weld's
# centre (um), every point up to 8 mm, every third beyond
_CLUMPED_V_UM = [
    5974, 5983, 5984, 5997, 6092, 6101, 6102, 6106, 6115, 6122, 6129, 6134, 6520, 6528, 6539, 6546, 6547, 6548,
    6551, 6553, 6553, 6557, 6966, 6974, 6982, 6986, 6987, 6991, 6998, 6999, 7004, 7090, 7093, 7094, 7096, 7421,
    7424, 7435, 7438, 7444, 7444, 7445, 7451, 7459, 7467, 7627, 7629, 7629, 7630, 7630, 7886, 7887, 7893, 7897,
    7902, 7903, 7904, 7904, 7911, 7919, 8155, 8162, 8360, 8366, 8379, 8662, 8665, 8832, 8840, 8858, 9176, 9188,
    9331, 9342, 9347, 9674, 9826, 9833, 9844, 9851, 10166, 10187, 10343, 10350, 10357, 10635, 10659, 10865, 10869,
    10878, 10905, 11142, 11162, 11392, 11416, 11418, 11468, 11631, 11755, 11938, 11947, 11958, 12057, 12107,
    12333, 12469, 12475, 12488, 12588, 12596, 12962, 12973, 12983, 13086, 13093, 13115, 13461, 13472, 13487,
    13593, 13599, 13621, 13956, 13963, 13979, 14091, 14103, 14376, 14459, 14469, 14477, 14597, 14636, 14946,
    14960, 14964, 15093, 15105, 15400, 15444, 15460, 15469, 15596, 15640, 15927, 15948, 15960]
_CLUMPED_H_UM = [
    404, 370, 358, 313, 305, 324, 291, 332, 318, 366, 348, 356, 135, 150, 173, 185, 148, 167, 202, 153, 183, 208,
    18, 34, 49, 53, 45, 49, 80, 64, 72, 47, 31, 20, 8, -76, -75, -53, -48, -64, -67, -37, -56, -41, -25, -82,
    -101, -117, -97, -113, -152, -155, -144, -161, -132, -124, -150, -153, -142, -126, -161, -187, -212, -211,
    -214, -247, -251, -273, -263, -259, -282, -300, -277, -300, -292, -293, -312, -300, -302, -294, -274, -311,
    -280, -296, -267, -244, -254, -235, -234, -225, -225, -201, -196, -172, -168, -153, -150, -127, -103, -74,
    -89, -45, -31, -34, 0, -8, -7, 16, 8, 2, -11, 12, 4, 5, -3, 12, -6, 17, -12, -1, -1, 5, 3, 11, 3, 12, 2, -1,
    7, 2, 0, -5, -2, -6, -12, 10, -7, -18, 4, 11, 3, 8, -7, -9, -1, -10, 5]


def test_a_sparsely_sampled_wall_straddling_the_plate_level_is_not_plate_left_beside_the_groove():
    """The flank runs into the groove through the plate's level between clumps of points (each
    clump spanning ~0.05 mm of height): its level points spread over ~0.5 mm but never form a
    stretch of plate (consecutive level points off the groove's circle): the toe is within its
    groove (old: the level points' extent, 0.5 mm, read as plate: 'not within', a false alarm).
    A stretch of real plate is still found (test above)."""
    v, h = np.array(_CLUMPED_V_UM) / 1000, np.array(_CLUMPED_H_UM) / 1000
    toe = fit_groove(v, h, settings=SETTINGS, side="plus", toe_guess_v=6.966)
    assert toe is not None and toe.groove.toe_within
    assert abs(toe.groove.depth.value - 0.30) < 0.02 and abs(toe.groove.width.value - 5.0) < 0.3


def test_plate_line_under_a_sticker_over_most_of_its_window():
    """A 9 mm paper sticker (0.1 mm) over 64 % of a 14 mm plate window: the least-median line
    lies on the sticker; the plate is the lowest band holding a fifth of the points, under it
    (old: the sticker's line, 0.1 mm high: the demo's grooves beside it 0.09 mm too deep, 0.8 mm
    too wide, failing their limits)."""
    rng = np.random.default_rng(4)
    u = rng.uniform(16, 30, 700)
    h = 10.0 - 0.035 * u + 0.006 * rng.standard_normal(700)
    h[(u > 18) & (u < 27)] += 0.1
    fit = fit_plate_line(u, h, min_points=8)
    assert abs(fit.slope + 0.035) < 0.002 and abs(fit.intercept - 10.0) < 0.02
    assert abs(fit.at(23.0) - (10.0 - 0.035 * 23.0)) < 0.005


# a plate window of the demo sample (top line, 45 mm, minus side; every second point): a paper
# sticker (0.1 mm) over its middle 5.7 mm, the plate on both sides of it (u in 0.01 mm, h in um)
_STICKER_MIDDLE_U = [
    -2952, -2905, -2879, -2848, -2846, -2823, -2797, -2753, -2748, -2705, -2669, -2653, -2651, -2650, -2648,
    -2645, -2637, -2630, -2610, -2608, -2602, -2600, -2599, -2597, -2591, -2587, -2570, -2566, -2558, -2555,
    -2550, -2546, -2544, -2543, -2527, -2523, -2508, -2506, -2503, -2497, -2494, -2484, -2477, -2460, -2457,
    -2453, -2447, -2444, -2442, -2438, -2426, -2416, -2406, -2405, -2399, -2396, -2395, -2392, -2379, -2373,
    -2356, -2354, -2348, -2345, -2343, -2334, -2331, -2310, -2305, -2299, -2296, -2294, -2288, -2283, -2267,
    -2260, -2255, -2251, -2250, -2248, -2245, -2244, -2237, -2224, -2213, -2204, -2201, -2198, -2195, -2192,
    -2185, -2168, -2159, -2154, -2150, -2147, -2144, -2140, -2121, -2117, -2105, -2102, -2100, -2098, -2096,
    -2094, -2092, -2072, -2068, -2053, -2050, -2048, -2045, -2044, -2031, -2024, -2007, -2004, -2000, -1997,
    -1994, -1992, -1986, -1973, -1967, -1950, -1950, -1948, -1947, -1945, -1924, -1921, -1903, -1901, -1900,
    -1899, -1897, -1896, -1881, -1874, -1860, -1852, -1850, -1848, -1847, -1846, -1836, -1822, -1814, -1800,
    -1799, -1799, -1796, -1774, -1772, -1753, -1752, -1750, -1750, -1748, -1746, -1732, -1726, -1710, -1702,
    -1700, -1700, -1699, -1697, -1697, -1686, -1674, -1665, -1652, -1651, -1649, -1649, -1646, -1646, -1625,
    -1622, -1603, -1601, -1600, -1599, -1598, -1598, -1597, -1582, -1579]
_STICKER_MIDDLE_H_UM = [
    138, 130, 120, 114, 107, 78, 95, 82, 75, 68, 53, 44, 45, 41, 46, 50, 34, 47, 31, 36, 36, 28, 39, 35, 35, 28,
    33, 14, 116, 108, 28, 116, 112, 123, 110, 111, 106, 110, 101, 83, 105, 103, 106, 83, 93, 77, 79, 72, 85, 92,
    78, 74, 68, 77, 72, 71, 70, 75, 55, 59, 58, 61, 41, 52, 54, 40, 32, 52, 46, 42, 51, 45, 48, 13, 27, 26, 30,
    11, 14, 25, 25, 33, 24, 11, 15, 17, 17, 24, 16, 13, 3, 4, -1, 0, 11, -6, -12, -16, -6, -21, -13, -5, -9, -15,
    -23, -13, -37, -34, -38, -30, -37, -40, -35, -37, -48, -48, -45, -50, -46, -41, -50, -54, -54, -61, -145,
    -176, -174, -170, -157, -162, -176, -176, -182, -178, -174, -178, -172, -178, -187, -194, -197, -195, -195,
    -197, -199, -199, -194, -210, -208, -209, -208, -211, -203, -220, -203, -218, -222, -213, -207, -225, -213,
    -239, -229, -233, -233, -245, -242, -237, -238, -243, -246, -247, -252, -257, -262, -250, -253, -251, -258,
    -254, -251, -269, -268, -268, -269, -278, -273, -265, -279, -278]


def test_plate_line_with_a_sticker_in_the_middle_of_its_window():
    """The plate on both sides of a sticker (-25.5 .. -19.8 mm): the least-median line is tilted
    across plate and sticker, the band under it is no plate; the line with the most points on it
    and none under it is, and of the two the plate's has the smaller RMS (old: a line across both,
    RMS 21 um, 0.8 deg too steep: the section failed its angular misalignment, 1.03 > 1 deg)."""
    u, h = np.array(_STICKER_MIDDLE_U) / 100, np.array(_STICKER_MIDDLE_H_UM) / 1000
    fit = fit_plate_line(u, h, min_points=8)
    on_plate = (u < -25.6) | (u > -19.7)
    assert fit.rms_mm < 0.008 and abs(fit.slope + 0.0303) < 0.002
    assert np.median(np.abs(h[on_plate] - fit.at(u[on_plate]))) < 0.01
    assert np.median(h[~on_plate] - fit.at(u[~on_plate])) > 0.07  # the sticker, above it


@pytest.mark.parametrize("seed", [0, 2])
def test_a_treated_weld_line_is_refined_through_its_grooves_centres(seed):
    """A treated cap on the manifest's line (centre x = 0), its grooves 3-6 mm wide varying along
    the weld on each side independently: the toes (where the grooves meet the weld) wander with
    the widths, ~1 mm; the grooves' centres a quarter of that. The line refined through the
    grooves' centres' midpoints stays within 0.2 mm and 0.6 deg of the weld (through the toes'
    midpoints: 0.76 mm off for seed 0, turned 1.46 deg for seed 2)."""
    config = WeldConfig(treatment="hfmi-treated", cap_height_mm=(2.0, 2.0), cap_width_mm=(16.0, 16.0),
                        flank_angle_deg=(30.0, 30.0), toe_radius_mm=(1.0, 1.0), ripple_amplitude_mm=(0.0, 0.0),
                        bead_wander_mm=0.0, undercut_probability=0.0, hfmi_groove_width_mm=(3.0, 6.0),
                        hfmi_groove_depth_mm=(0.2, 0.5))
    cap = draw_weld_cap(config, np.random.default_rng(seed), centre_x_mm=0.0, y_extent_mm=50.0)
    rng = np.random.default_rng(5)
    x, y = rng.uniform(-32, 32, 150_000), rng.uniform(-30, 30, 150_000)
    z = 10.0 + cap.height_mm(x, y)[0] + 0.005 * rng.standard_normal(len(x))
    found = measure_weld_line(np.stack([x, y, z], 1), np.tile([0.0, 0.0, 1.0], (len(x), 1)),
                              np.array([[0.0, -30.0, 10.0], [0.0, 30.0, 10.0]]), name="top", step_mm=2.0,
                              section_half_width_mm=0.5, reach_mm=32.0, end_margin_mm=2.0, min_normal_cos=0.2,
                              settings=SETTINGS, treated=True)
    assert len(found.sections) >= 25
    assert all(s.axis_mm is not None for s in found.sections if all(t is not None and t.groove for t in s.toes))
    assert abs(found.offset_mm) < 0.2 and abs(found.turn_deg) < 0.6, (found.offset_mm, found.turn_deg)


# another plate window of the demo sample (top line, 12 mm, minus side; every third point): a
# sticker over -27.4 .. -21.6 mm, nearly half of the points, the plate mostly on its near side
_STICKER_HALF_U = [
    -2932, -2898, -2868, -2826, -2787, -2776, -2767, -2743, -2741, -2728, -2724, -2719, -2717, -2700, -2691,
    -2682, -2675, -2670, -2669, -2660, -2645, -2639, -2628, -2625, -2619, -2618, -2600, -2597, -2589, -2578,
    -2574, -2570, -2569, -2553, -2548, -2538, -2528, -2524, -2520, -2511, -2506, -2489, -2488, -2477, -2474,
    -2471, -2468, -2459, -2447, -2438, -2435, -2425, -2422, -2420, -2404, -2398, -2388, -2376, -2374, -2372,
    -2364, -2347, -2339, -2338, -2325, -2322, -2318, -2316, -2296, -2289, -2288, -2275, -2273, -2271, -2254,
    -2245, -2239, -2225, -2223, -2222, -2210, -2196, -2189, -2175, -2173, -2171, -2168, -2144, -2136, -2127,
    -2126, -2120, -2096, -2086, -2078, -2077, -2070, -2047, -2037, -2029, -2027, -2020, -2000, -1995, -1986,
    -1977, -1975, -1953, -1948, -1936, -1930, -1928, -1923, -1910, -1899, -1886, -1880, -1877, -1874, -1867,
    -1847, -1835, -1834, -1827, -1821, -1803, -1785, -1783, -1778, -1776, -1773, -1760, -1749, -1734, -1732,
    -1727, -1726, -1721, -1708, -1695, -1683, -1677, -1677, -1674, -1659, -1652, -1634, -1633, -1627, -1627,
    -1622, -1610, -1598, -1585, -1583, -1577, -1575, -1567, -1560]
_STICKER_HALF_H_UM = [
    128, 115, 109, 98, 76, 77, 77, 160, 168, 170, 163, 157, 151, 159, 161, 158, 148, 153, 168, 157, 146, 136, 139,
    134, 141, 140, 124, 122, 126, 125, 113, 111, 129, 103, 118, 111, 97, 107, 106, 112, 101, 92, 100, 83, 90, 89,
    80, 78, 95, 79, 68, 64, 70, 88, 75, 77, 57, 49, 64, 55, 57, 66, 46, 56, 36, 48, 49, 42, 44, 41, 33, 25, 28,
    31, 16, 13, 25, 17, 2, 38, -6, 6, 10, -3, -11, -7, 2, -106, -107, -122, -115, -121, -129, -136, -136, -126,
    -138, -151, -128, -146, -155, -146, -156, -151, -155, -162, -161, -166, -163, -173, -181, -185, -185, -173,
    -182, -193, -207, -190, -193, -197, -203, -213, -205, -205, -197, -226, -224, -218, -222, -216, -225, -229,
    -231, -241, -247, -240, -228, -239, -247, -254, -255, -255, -260, -268, -261, -257, -266, -268, -281, -265,
    -273, -275, -279, -278, -287, -291, -285, -293, -300]


def test_plate_line_with_a_sticker_over_half_of_its_window():
    """A line tilted across the sticker's near edge and the plate holds more points within 0.03 mm
    than the plate's own line, with a few tens under it: each point under a line costs it five
    points on it (two were not enough: the tilted line won, the groove beside it read 0.10 mm
    too shallow)."""
    u, h = np.array(_STICKER_HALF_U) / 100, np.array(_STICKER_HALF_H_UM) / 1000
    fit = fit_plate_line(u, h, min_points=8)
    on_plate = (u < -27.5) | (u > -21.5)
    assert fit.rms_mm < 0.008 and abs(fit.slope + 0.0305) < 0.002
    assert np.median(np.abs(h[on_plate] - fit.at(u[on_plate]))) < 0.01
    assert np.median(h[~on_plate] - fit.at(u[~on_plate])) > 0.07
