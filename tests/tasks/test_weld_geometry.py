"""The section fits recover the drawn weld: the simulator's own cap (power-law flank, toe fillet,
undercut, HFMI groove) sampled as a profile at the paper's 0.02 mm, with and without sensor noise;
an under-treated groove fails its limits, located; bad settings and limits are refused by field."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from data_catalog.acceptance import load_acceptance_limits
from flows.preflight import load_config
from schemas.reconstruction import WeldGeometryConfig
from schemas.simulation import WeldConfig
from simulator.weld import draw_weld_cap
from tasks.weld_acceptance import judge_weld
from tasks.weld_fits import SectionSettings, fit_plate_line
from tasks.weld_geometry import along_weld_statistics, measure_section, measure_weld_line

DEFAULTS = WeldGeometryConfig()
SETTINGS = SectionSettings(plate_window_mm=DEFAULTS.plate_window_mm, toe_window_mm=DEFAULTS.toe_window_mm,
                           toe_threshold_mm=DEFAULTS.toe_threshold_mm, groove_min_depth_mm=DEFAULTS.groove_min_depth_mm,
                           groove_plate_gap_mm=DEFAULTS.groove_plate_gap_mm,
                           undercut_min_depth_mm=DEFAULTS.undercut_min_depth_mm,
                           height_half_width_mm=DEFAULTS.height_half_width_mm, min_points=DEFAULTS.min_points)


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
        assert abs(toe.radius.value - radius) <= tol_r, (toe.side, toe.radius)
        assert abs(toe.flank_angle_deg.value - flank) <= tol_a, (toe.side, toe.flank_angle_deg)
        assert np.isfinite(toe.radius.sigma) and np.isfinite(toe.flank_angle_deg.sigma)
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
        assert toe.radius.value == g.radius.value  # a treated toe's radius is its groove's
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
