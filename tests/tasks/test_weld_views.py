"""The weld as the QA page draws it (tasks.weld_views), on weld documents made in memory: the
failing sections are drawn first, the figures along the weld carry their limits and failing
marks, a section's points are cut and placed in its plane with its toes and the plate face."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from schemas.acceptance import AcceptanceRule, FigureLimits
from schemas.weld_document import (FilletToes, FilletWeldSection, Figure, Finding, SectionToes, ToeFigures, WeldGeometry,
                                   WeldLineFound, WeldSection)
from tasks.weld_views import (along_weld_series, chosen_sections, figure_value, near_sections, section_cut,
                              toe_closeups)


def _f(value: float | None, sigma: float | None = 0.1) -> Figure:
    return Figure(value=value, sigma=None if value is None else sigma)


def _toe(side: str, u_mm: float, radius_mm: float | None = 1.5) -> ToeFigures:
    return ToeFigures(side=side, position_u_mm=u_mm, position_sigma_mm=0.05, flank_angle_deg=_f(30.0),
                      toe_radius_mm=_f(radius_mm), undercut_depth_mm=_f(0.0), fit_rms_mm=0.01, points=30,
                      treated=False)


def _section(line: str, position_mm: float, *, verdict: str = "pass", violations: int = 0, width_mm: float | None = 10.0,
             toes: tuple[float, float] | None = (-5.0, 6.0), centre=(0.0, 0.0, 2.0)) -> WeldSection:
    found = [Finding(line=line, position_mm=position_mm, toe="minus", figure="toe_radius_mm", value=0.1, limit=">= 1")
             for _ in range(violations)]
    return WeldSection(line=line, position_mm=position_mm, centre_specimen_mm=centre, points=500,
                       reinforcement_height_mm=_f(2.0), reinforcement_width_mm=_f(width_mm),
                       axial_misalignment_mm=_f(0.1), angular_misalignment_deg=_f(0.2),
                       toes=SectionToes(minus=_toe("minus", toes[0]) if toes else None,
                                        plus=_toe("plus", toes[1]) if toes else None),
                       passed={"pass": True, "fail": False, "uncertain": True}[verdict], verdict=verdict,
                       violations=found, uncertain=[])


_LINE = WeldLineFound(name="top", sections=10, offset_mm=0.0, turn_deg=0.0, face_normal=(0.0, 0.0, 1.0),
                      across=(1.0, 0.0, 0.0), measured_extent_mm=(0.0, 9.0))


def _geometry(sections: list[WeldSection], **kwargs) -> WeldGeometry:
    failing = [f for s in sections for f in s.violations]
    return WeldGeometry(measured=True, joint="butt", treatment="as-welded", lines=[_LINE], sections=sections,
                        failing=failing, **kwargs)


def _line_of_ten() -> list[WeldSection]:
    """Ten sections 0..9 mm along one line: 3 fails once, 8 fails twice, 5 is uncertain."""
    verdicts = {3: ("fail", 1), 5: ("uncertain", 0), 8: ("fail", 2)}
    return [_section("top", float(k), verdict=verdicts.get(k, ("pass", 0))[0], violations=verdicts.get(k, ("pass", 0))[1])
            for k in range(10)]


# --- which sections are drawn ---
def test_the_failing_sections_are_drawn_first_the_worst_first():
    geometry = _geometry(_line_of_ten())
    assert [s.position_mm for s in chosen_sections(geometry, 1)] == [8.0]  # two violations beat one
    assert [s.position_mm for s in chosen_sections(geometry, 2)] == [3.0, 8.0]  # then in order along the line
    assert [s.position_mm for s in chosen_sections(geometry, 3)] == [3.0, 5.0, 8.0]  # then the uncertain


def test_the_rest_is_filled_evenly_along_the_line_its_ends_left_out():
    sections = [_section("top", float(k)) for k in range(9)]
    assert [s.position_mm for s in chosen_sections(_geometry(sections), 3)] == [2.0, 4.0, 6.0]
    assert [s.position_mm for s in chosen_sections(_geometry(_line_of_ten()), 4)] == [3.0, 4.0, 5.0, 8.0]
    assert len(chosen_sections(_geometry(sections[:2]), 5)) == 2  # fewer than asked: all of them
    assert chosen_sections(_geometry(sections), 0) == []
    with pytest.raises(ValueError, match="per_line must not be negative"):
        chosen_sections(_geometry(sections), -1)


def test_each_line_gets_its_own_sections():
    sections = [_section("top", float(k)) for k in range(5)] + [_section("bottom", float(k)) for k in range(5)]
    chosen = chosen_sections(_geometry(sections), 1)
    assert [(s.line, s.position_mm) for s in chosen] == [("top", 2.0), ("bottom", 2.0)]


# --- the figures along the weld ---
def test_the_figures_along_the_weld_carry_the_limits_and_the_failing_sections():
    sections = _line_of_ten()
    sections[4] = _section("top", 4.0, toes=None)  # no toe fitted there: NaN on the toe curves
    rule = AcceptanceRule(joint="butt", treatment="as-welded", source="test", toe_radius_mm=FigureLimits(min=1.0),
                          reinforcement_height_mm=FigureLimits(max=3.0))
    series = along_weld_series(_geometry(sections, acceptance=rule))
    assert [s.figure for s in series] == ["toe radius", "flank angle", "undercut", "height", "width", "axial misal.",
                                          "angular misal."]  # as welded: no groove
    radius = series[0]
    assert (radius.unit, radius.limit_min, radius.limit_max) == ("mm", 1.0, None)
    assert list(radius.curves) == ["top minus toe", "top plus toe"]
    position, value, sigma, failing = radius.curves["top minus toe"]
    assert_allclose(position, np.arange(10.0))
    assert np.isnan(value[4]) and np.isnan(sigma[4]) and value[0] == 1.5 and sigma[0] == 0.1
    assert failing.dtype == bool and np.flatnonzero(failing).tolist() == [3, 8]
    # a finding marks its figure at its section (both toes' curves), no other figure
    assert np.flatnonzero(radius.curves["top plus toe"][3]).tolist() == [3, 8]
    assert not any(curve[3].any() for s in series[1:] for curve in s.curves.values())
    assert (series[3].limit_min, series[3].limit_max) == (None, 3.0)
    assert list(series[3].curves) == ["top"]


def test_a_toe_never_measured_has_no_curve_and_an_unmeasured_weld_no_series():
    series = along_weld_series(_geometry([_section("top", float(k), toes=None) for k in range(3)]))
    assert [s.figure for s in series] == ["height", "width", "axial misal.", "angular misal."]
    with pytest.raises(ValueError, match="the weld was not measured"):
        along_weld_series(WeldGeometry(measured=False, why_not="no placement", joint=None, treatment=None))


def test_a_figure_not_determined_is_nan():
    assert figure_value(Figure(value=2.0, sigma=0.5)) == (2.0, 0.5)
    assert math.isnan(figure_value(Figure(value=2.0, sigma=None))[1])
    assert all(math.isnan(v) for v in figure_value(None) + figure_value(Figure(value=None, sigma=None)))


# --- a section's picture ---
def test_a_section_cut_keeps_the_points_in_its_slab_in_its_plane():
    rng = np.random.default_rng(0)
    points = np.c_[rng.uniform(-40, 40, 5000), rng.uniform(-5, 5, 5000), rng.uniform(-20, 20, 5000)]
    centre = (1.0, 2.0, 3.0)
    cut = section_cut(points, _section("top", 2.0, centre=centre), _LINE, half_width_mm=0.5, reach_mm=32.0,
                      bounds_mm=((-50.0, -10.0, -4.0), (50.0, 10.0, 4.0)))
    d = points - centre
    inside = (np.abs(d[:, 1]) <= 0.5) & (np.abs(d[:, 0]) <= 32.0) & (np.abs(d[:, 2]) <= 16.0)
    assert_allclose(cut.u_mm, d[inside, 0])  # across: x
    assert_allclose(cut.h_mm, d[inside, 2])  # up: the face normal, z
    assert cut.toes == [(-5.5, "minus toe"), (5.5, "plus toe")]  # from the toes' midpoint, 0.5
    ((u, h, label),) = cut.plate
    assert label == "the drawing's plate face"
    assert_allclose(u, [-32.0, 32.0])
    assert_allclose(h, [1.0, 1.0])  # the plate's top at z 4, the centre at z 3
    assert cut.half_span_mm == 11.0  # half the width, 10 mm, plus 6


def test_a_section_cut_without_toes_width_or_drawing():
    section = _section("top", 2.0, toes=None, width_mm=None)
    cut = section_cut(np.zeros((0, 3)), section, _LINE, half_width_mm=0.5, reach_mm=10.0)
    assert cut.toes == [] and cut.plate == [] and cut.u_mm.shape == (0,)
    assert cut.half_span_mm == 10.0  # half the reach plus 6, at most the reach
    upright = _LINE.model_copy(update={"face_normal": (1.0, 0.0, 0.0), "across": (0.0, 0.0, 1.0)})
    assert section_cut(np.zeros((1, 3)), section, upright, half_width_mm=0.5, reach_mm=10.0,
                       bounds_mm=((-1, -1, -1), (1, 1, 1))).plate == []  # a face not facing z: no plate line
    with pytest.raises(ValueError, match="must be positive"):
        section_cut(np.zeros((1, 3)), section, _LINE, half_width_mm=0.0, reach_mm=10.0)
    with pytest.raises(ValueError, match=r"points_mm must be \(n, 3\)"):
        section_cut(np.zeros(3), section, _LINE, half_width_mm=0.5, reach_mm=10.0)


def _fillet(position_mm: float, centre) -> FilletWeldSection:
    none = Figure(value=None, sigma=None)
    return FilletWeldSection(line="tilted", position_mm=position_mm, centre_specimen_mm=centre, points=500,
                             base_direction=(0.0, math.cos(0.3), math.sin(0.3)), stem_direction=(0.0, -math.sin(0.3),
                                                                                                  math.cos(0.3)),
                             plates_angle_deg=90.0, leg_base_mm=none, leg_stem_mm=none, throat_mm=none, convexity_mm=none,
                             toes=FilletToes(base=_toe("base", 6.0), stem=_toe("stem", 7.0)), passed=None, verdict=None,
                             violations=[], uncertain=[])


def test_each_sections_neighbourhood_gives_the_cut_and_close_ups_all_points_give():
    """A line along x on a face tilted 0.3 rad about x: butt and fillet sections' cuts and toe
    close-ups from their neighbourhoods are those from the whole cloud, from a small part of it."""
    rng = np.random.default_rng(4)
    points = np.c_[rng.uniform(-100, 100, 1_000_000), rng.uniform(-30, 30, 1_000_000), rng.uniform(-30, 30, 1_000_000)]
    c, s_ = math.cos(0.3), math.sin(0.3)
    line = WeldLineFound(name="tilted", sections=3, offset_mm=0.0, turn_deg=0.0, face_normal=(0.0, -s_, c),
                         across=(0.0, c, s_), measured_extent_mm=(-80.0, 80.0))
    sections = [_section("tilted", x, centre=(x, 1.0, 2.0), toes=(-4.0, 5.0)) for x in (-60.0, 0.0, 55.5)]
    sections.append(_fillet(20.0, (20.0, -3.0, 1.0)))
    near = near_sections(points, sections, line, half_width_mm=0.5, reach_mm=15.0)
    assert len(near) == len(sections)
    for section, part in zip(sections, near):
        # each selection's box is 1 mm across the line: a thin slab of a 200 x 60 x 60 mm block of points,
        # not the box around the selection's bounding sphere (34 mm)
        assert len(part) < len(points) / 100
        whole = section_cut(points, section, line, half_width_mm=0.5, reach_mm=15.0)
        cut = section_cut(part, section, line, half_width_mm=0.5, reach_mm=15.0)
        assert len(whole.u_mm) > 100 and np.array_equal(cut.u_mm, whole.u_mm) and np.array_equal(cut.h_mm, whole.h_mm)
        close, close_whole = (toe_closeups(p, section, line, half_width_mm=0.5) for p in (part, points))
        assert len(close) == 2
        for a, b in zip(close, close_whole):
            assert len(b.t_mm) > 10 and np.array_equal(a.t_mm, b.t_mm) and np.array_equal(a.n_mm, b.n_mm)
