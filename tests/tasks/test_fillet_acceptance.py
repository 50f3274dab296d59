"""A fillet weld judged against the catalog's rule (``tasks.weld_acceptance.judge_fillet_weld``):
each limited figure fails, straddles (uncertain) or passes, and a section without both toes is not
measured, never passed."""

from __future__ import annotations

import math

import pytest

from data_catalog.acceptance import load_acceptance_limits
from tasks.fillet_section import FilletSection
from tasks.weld_acceptance import judge_fillet_weld
from tasks.weld_fits import Measured, ToeFit

RULE = load_acceptance_limits(None).rule_for("fillet", "as-welded")


def _toe(side: str, leg_mm: float, angle_deg: float = 50.0, undercut_mm: float = 0.0) -> ToeFit:
    return ToeFit(side=side, position_u_mm=leg_mm, position_sigma_mm=0.02, flank_angle_deg=Measured(angle_deg, 0.5),
                  notch_radius=Measured(0.8, 0.05), undercut_depth=Measured(undercut_mm, 0.01), groove=None,
                  rms_mm=0.01, n_points=60)


def _section(*, leg_base=7.0, leg_stem=6.0, convexity=0.8, convexity_sigma=0.02, base_angle=50.0, stem=True,
             undercut=0.0, throat=4.6) -> FilletSection:
    """A section of a 90 deg T: each toe at its leg from the root."""
    return FilletSection(root_ab_mm=(0.0, 0.0), base_direction=(1.0, 0.0), stem_direction=(0.0, 1.0),
                         plates_angle_deg=90.0, base_toe=_toe("base", leg_base, base_angle, undercut),
                         stem_toe=_toe("stem", leg_stem) if stem else None, leg_base=Measured(leg_base, 0.03),
                         leg_stem=Measured(leg_stem, 0.03), throat=Measured(throat, 0.03),
                         convexity=Measured(convexity, convexity_sigma), n_points=900)


def _judge(**kw):
    return judge_fillet_weld([("fillet-pos", 10.0, _section(**kw))], RULE)


def test_the_catalog_has_a_fillet_rule_for_every_fillet_joint_and_treatment():
    limits = load_acceptance_limits(None)
    for joint in ("fillet", "double fillet", "cruciform fillet"):
        for treatment in ("as-welded", "hfmi-treated"):
            rule = limits.rule_for(joint, treatment)
            assert rule is not None and rule.convexity_mm.max == 4.0 and rule.convexity_allowance.per_mm == 0.15
            assert rule.leg_asymmetry_allowance.base_mm == 2.0
    assert limits.rule_for("fillet", "hfmi-treated").groove_required


def test_a_weld_within_every_limit_passes():
    verdict = _judge()
    assert verdict.passed and verdict.n_measured == 1 and verdict.sections[0].verdict == "pass"


# ISO 5817 level C as the catalog has it: convexity <= 1 + 0.15 b (b the face between the toes:
# legs 7 and 6 -> 9.22 mm -> 2.383 mm), legs' difference <= 2 + 0.15 a (a 4.6 -> 2.69 mm)
@pytest.mark.parametrize(("kw", "figure", "toe", "limit"), [
    (dict(convexity=2.6), "convexity_mm", None, "<= 2.383"),
    (dict(leg_base=12.0, leg_stem=12.0, convexity=2.6, throat=9.0), None, None, None),  # b 16.97: 3.546 allowed
    (dict(leg_base=12.0, leg_stem=12.0, convexity=3.9, throat=9.0), "convexity_mm", None, "<= 3.546"),
    (dict(leg_base=17.0, leg_stem=17.0, convexity=4.2, throat=12.0), "convexity_mm", None, "<= 4"),  # the cap
    (dict(leg_base=9.0, leg_stem=6.0), "leg_asymmetry_mm", None, "<= 2.69 (magnitude)"),
    (dict(leg_base=6.0, leg_stem=9.0), "leg_asymmetry_mm", None, "<= 2.69 (magnitude)"),  # either way round
    (dict(base_angle=84.0), "flank_angle_deg", "base", "<= 80"),
    (dict(undercut=0.8), "undercut_depth_mm", "base", "<= 0.5"),
])
def test_a_figure_past_its_limit_fails_the_section_naming_it(kw, figure, toe, limit):
    verdict = _judge(**kw)
    if figure is None:
        assert verdict.passed and verdict.sections[0].verdict == "pass"
        return
    assert not verdict.passed and verdict.n_failing == 1
    (found,) = verdict.sections[0].violations
    assert (found.figure, found.toe, found.limit, found.line, found.position_mm) == (figure, toe, limit, "fillet-pos", 10.0)


def test_a_figure_within_its_sigma_of_a_limit_is_uncertain_not_failed():
    verdict = _judge(convexity=2.35, convexity_sigma=0.1)  # 2.383 allowed
    assert verdict.passed and verdict.n_uncertain == 1 and verdict.sections[0].verdict == "uncertain"
    assert [u.figure for u in verdict.sections[0].uncertain] == ["convexity_mm"]


def test_the_legs_difference_carries_both_legs_sigmas():
    # 2.72 mm apart, each leg +-0.03: the difference's 1-sigma 0.042 puts 2.69 within it (one leg's
    # 0.03 would not)
    verdict = _judge(leg_base=8.72, leg_stem=6.0)
    (unsure,) = verdict.sections[0].uncertain
    assert unsure.figure == "leg_asymmetry_mm" and math.isclose(unsure.sigma, round(math.hypot(0.03, 0.03), 4))


def test_a_section_without_its_stem_toe_is_not_measured_and_a_weld_of_none_does_not_pass():
    verdict = _judge(stem=False)
    assert verdict.n_measured == 0 and verdict.n_not_measured == 1 and not verdict.passed
    assert verdict.sections[0].verdict == "not measured"
