"""The measured weld judged against its acceptance limits (``schemas.acceptance``): each section
passes, fails or is uncertain, failing and uncertain sections located (weld line, toe, position
along the line), the weld as a whole. A figure is judged on its measured value and its 1-sigma:

- outside a limit by more than ``uncertain_sigmas`` of its sigma: a violation (the section fails);
- within ``uncertain_sigmas`` of its sigma of a limit, on either side: uncertain (the measurement
  cannot tell on which side of the limit the figure lies): listed for a person to look at, the
  section neither failed nor passed silently (its ``verdict`` says "uncertain");
- a figure without a sigma (NaN) is judged on its value alone;
- a limited figure the fits could not determine (NaN: e.g. a groove's width where its circle is not
  held on both sides of its bottom) is uncertain, "not measured".

A section or toe that could not be measured is listed as such, never passed; the weld passes when
at most ``max_failing_fraction`` of its measured sections fail (uncertain sections do not fail it)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from schemas.acceptance import AcceptanceRule, FigureLimits
from tasks.weld_fits import Measured
from tasks.weld_geometry import SectionMeasurement

__all__ = ["Violation", "SectionVerdict", "WeldVerdict", "judge_weld", "check_figure"]


@dataclass(frozen=True)
class Violation:
    line: str
    position_mm: float
    toe: str | None  # "minus" / "plus", None for a section figure
    figure: str
    value: float | None
    limit: str  # e.g. ">= 0.2", "groove required"
    sigma: float | None = None  # the figure's 1-sigma, where it has one


@dataclass(frozen=True)
class SectionVerdict:
    line: str
    position_mm: float
    measured: bool
    passed: bool  # measured and no violation (an uncertain section has passed no limit for certain either)
    violations: list[Violation]
    uncertain: list[Violation] = field(default_factory=list)  # figures within their sigma(s) of a limit

    @property
    def verdict(self) -> str:
        if not self.measured:
            return "not measured"
        return "fail" if self.violations else "uncertain" if self.uncertain else "pass"


@dataclass(frozen=True)
class WeldVerdict:
    passed: bool
    sections: list[SectionVerdict]
    n_measured: int
    n_failing: int
    n_not_measured: int
    failing_fraction: float
    max_failing_fraction: float
    n_uncertain: int = 0  # measured sections that do not fail but have an uncertain figure


def check_figure(limits: FigureLimits, value: Measured, *, magnitude: bool = False,
                 sigmas: float = 1.0) -> tuple[str | None, bool]:
    """(the limit broken or straddled, e.g. ">= 0.2", or "not measured", or None; whether it is
    certain). A value
    outside a limit by more than ``sigmas`` of its 1-sigma breaks it for certain; within that of
    the limit on either side it straddles it (uncertain). No sigma: the value alone decides."""
    v, sd = value.value, value.sigma
    if not math.isfinite(v):  # a limited figure the fits could not determine: nobody can tell
        return ("not measured", False) if limits.min is not None or limits.max is not None else (None, True)
    v = abs(v) if magnitude else v
    band = sigmas * sd if math.isfinite(sd) and sd > 0 else 0.0
    for bound, op, outside in ((limits.min, ">=", lambda b: v < b), (limits.max, "<=", lambda b: v > b)):
        if bound is None:
            continue
        if abs(v - bound) < band:
            return f"{op} {bound:g}", False
        if outside(bound):
            return f"{op} {bound:g}", True
    return None, True


def judge_weld(sections: list[SectionMeasurement], rule: AcceptanceRule) -> WeldVerdict:
    verdicts = []
    for sec in sections:
        found: list[Violation] = []
        unsure: list[Violation] = []

        def add(toe, figure, value: Measured, limits: FigureLimits, magnitude=False):
            why, certain = check_figure(limits, value, magnitude=magnitude, sigmas=rule.uncertain_sigmas)
            if why:
                sd = value.sigma if math.isfinite(value.sigma) else None
                (found if certain else unsure).append(Violation(
                    sec.line, sec.position_mm, toe, figure,
                    round(float(value.value), 4) if math.isfinite(value.value) else None,
                    why + (" (magnitude)" if magnitude else ""), None if sd is None else round(float(sd), 4)))

        measured = all(t is not None for t in sec.toes) and math.isfinite(sec.height.value)
        if measured:
            add(None, "reinforcement_height_mm", sec.height, rule.reinforcement_height_mm)
            add(None, "reinforcement_width_mm", sec.width, rule.reinforcement_width_mm)
            add(None, "axial_misalignment_mm", sec.axial_misalignment, rule.axial_misalignment_mm, True)
            add(None, "angular_misalignment_deg", sec.angular_misalignment_deg, rule.angular_misalignment_deg, True)
            for toe in sec.toes:
                add(toe.side, "toe_radius_mm", toe.notch_radius, rule.toe_radius_mm)
                add(toe.side, "flank_angle_deg", toe.flank_angle_deg, rule.flank_angle_deg)
                add(toe.side, "undercut_depth_mm", toe.undercut_depth, rule.undercut_depth_mm)
                if toe.groove is None:
                    if rule.groove_required:
                        found.append(Violation(sec.line, sec.position_mm, toe.side, "groove", None, "groove required"))
                    continue
                add(toe.side, "groove_depth_mm", toe.groove.depth, rule.groove_depth_mm)
                add(toe.side, "groove_width_mm", toe.groove.width, rule.groove_width_mm)
                add(toe.side, "groove_radius_mm", toe.groove.radius, rule.groove_radius_mm)
                if rule.toe_within_groove and not toe.groove.toe_within:
                    found.append(Violation(sec.line, sec.position_mm, toe.side, "toe_within_groove", None,
                                           "toe fully within the groove"))
        verdicts.append(SectionVerdict(sec.line, sec.position_mm, measured, measured and not found, found,
                                       unsure if measured else []))
    n_measured = sum(v.measured for v in verdicts)
    n_failing = sum(v.measured and not v.passed for v in verdicts)
    fraction = n_failing / n_measured if n_measured else 1.0
    return WeldVerdict(passed=n_measured > 0 and fraction <= rule.max_failing_fraction, sections=verdicts,
                       n_measured=n_measured, n_failing=n_failing, n_not_measured=len(verdicts) - n_measured,
                       failing_fraction=fraction, max_failing_fraction=rule.max_failing_fraction,
                       n_uncertain=sum(v.verdict == "uncertain" for v in verdicts))
