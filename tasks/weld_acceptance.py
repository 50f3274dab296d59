"""The measured weld judged against its acceptance limits (``schemas.acceptance``), a butt weld's
sections (``judge_weld``) or a fillet weld's (``judge_fillet_weld``): each section passes, fails or
is uncertain, failing and uncertain sections located (weld line, toe, position
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

from schemas.acceptance import AcceptanceRule, Allowance, FigureLimits
from tasks.fillet_section import FilletSection
from tasks.weld_fits import Measured, ToeFit
from tasks.weld_geometry import SectionMeasurement

__all__ = ["Violation", "SectionVerdict", "WeldVerdict", "judge_weld", "judge_fillet_weld", "check_figure", "section_measured",
           "fillet_section_measured"]


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


class _Findings:
    """A section's violations and uncertain figures as they are judged (``check_figure``)."""

    def __init__(self, line: str, position_mm: float, sigmas: float):
        self.line, self.position_mm, self.sigmas = line, position_mm, sigmas
        self.found: list[Violation] = []
        self.unsure: list[Violation] = []

    def add(self, toe, figure: str, value: Measured, limits: FigureLimits, magnitude: bool = False) -> None:
        why, certain = check_figure(limits, value, magnitude=magnitude, sigmas=self.sigmas)
        if why:
            sd = value.sigma if math.isfinite(value.sigma) else None
            (self.found if certain else self.unsure).append(Violation(
                self.line, self.position_mm, toe, figure,
                round(float(value.value), 4) if math.isfinite(value.value) else None,
                why + (" (magnitude)" if magnitude else ""), None if sd is None else round(float(sd), 4)))

    def toe(self, toe: ToeFit, side: str, rule: AcceptanceRule) -> None:
        """A toe's figures: radius, flank angle, undercut, and a treated toe's groove."""
        self.add(side, "toe_radius_mm", toe.notch_radius, rule.toe_radius_mm)
        self.add(side, "flank_angle_deg", toe.flank_angle_deg, rule.flank_angle_deg)
        self.add(side, "undercut_depth_mm", toe.undercut_depth, rule.undercut_depth_mm)
        if toe.groove is None:
            if rule.groove_required:
                self.found.append(Violation(self.line, self.position_mm, side, "groove", None, "groove required"))
            return
        self.add(side, "groove_depth_mm", toe.groove.depth, rule.groove_depth_mm)
        self.add(side, "groove_width_mm", toe.groove.width, rule.groove_width_mm)
        self.add(side, "groove_radius_mm", toe.groove.radius, rule.groove_radius_mm)
        if rule.toe_within_groove and not toe.groove.toe_within:
            self.found.append(Violation(self.line, self.position_mm, side, "toe_within_groove", None,
                                        "toe fully within the groove"))

    def verdict(self, measured: bool) -> SectionVerdict:
        return SectionVerdict(self.line, self.position_mm, measured, measured and not self.found, self.found,
                              self.unsure if measured else [])


def _weld_verdict(verdicts: list[SectionVerdict], rule: AcceptanceRule) -> WeldVerdict:
    n_measured = sum(v.measured for v in verdicts)
    n_failing = sum(v.measured and not v.passed for v in verdicts)
    fraction = n_failing / n_measured if n_measured else 1.0
    return WeldVerdict(passed=n_measured > 0 and fraction <= rule.max_failing_fraction, sections=verdicts,
                       n_measured=n_measured, n_failing=n_failing, n_not_measured=len(verdicts) - n_measured,
                       failing_fraction=fraction, max_failing_fraction=rule.max_failing_fraction,
                       n_uncertain=sum(v.verdict == "uncertain" for v in verdicts))


def section_measured(sec: SectionMeasurement) -> bool:
    """A butt section is measured when both its toes and its height are."""
    return all(t is not None for t in sec.toes) and math.isfinite(sec.height.value)


def fillet_section_measured(sec: FilletSection) -> bool:
    """A fillet section is measured when both its toes and both its legs are."""
    return (sec.base_toe is not None and sec.stem_toe is not None
            and math.isfinite(sec.leg_base.value) and math.isfinite(sec.leg_stem.value))


def judge_weld(sections: list[SectionMeasurement], rule: AcceptanceRule) -> WeldVerdict:
    """A butt weld's sections judged by ``rule`` (module description)."""
    verdicts = []
    for sec in sections:
        f = _Findings(sec.line, sec.position_mm, rule.uncertain_sigmas)
        measured = section_measured(sec)
        if measured:
            f.add(None, "reinforcement_height_mm", sec.height, rule.reinforcement_height_mm)
            f.add(None, "reinforcement_width_mm", sec.width, rule.reinforcement_width_mm)
            f.add(None, "axial_misalignment_mm", sec.axial_misalignment, rule.axial_misalignment_mm, True)
            f.add(None, "angular_misalignment_deg", sec.angular_misalignment_deg, rule.angular_misalignment_deg, True)
            for toe in sec.toes:
                f.toe(toe, toe.side, rule)
        verdicts.append(f.verdict(measured))
    return _weld_verdict(verdicts, rule)


def _grown(limits: FigureLimits, allowance: Allowance | None, size_mm: float) -> FigureLimits:
    """``limits`` with its maximum lowered to ``allowance`` at ``size_mm`` where that is smaller
    (no allowance, or a size not measured: ``limits`` as they are)."""
    if allowance is None or not math.isfinite(size_mm):
        return limits
    grown = round(allowance.at(size_mm), 3)
    return FigureLimits(min=limits.min, max=grown if limits.max is None else min(limits.max, grown))


def judge_fillet_weld(sections: list[tuple[str, float, FilletSection]], rule: AcceptanceRule) -> WeldVerdict:
    """A fillet weld's sections ((line, position along it, section)) judged by ``rule``: each leg,
    the throat, the convexity (its limit grown with the face's width between the toes where the
    rule says so), the legs' difference (its 1-sigma from theirs; its limit grown with the measured
    throat), and both toes ("base", "stem") as a butt weld's. A section without both toes and its legs is not measured."""
    verdicts = []
    for line, position, sec in sections:
        f = _Findings(line, position, rule.uncertain_sigmas)
        measured = fillet_section_measured(sec)
        if measured:
            f.add(None, "leg_base_mm", sec.leg_base, rule.limits("leg_base_mm"))  # the document's figures
            f.add(None, "leg_stem_mm", sec.leg_stem, rule.limits("leg_stem_mm"))
            f.add(None, "throat_mm", sec.throat, rule.throat_mm)
            base, stem = sec.toe_ab_mm("base"), sec.toe_ab_mm("stem")
            face_width = math.hypot(base[0] - stem[0], base[1] - stem[1])
            f.add(None, "convexity_mm", sec.convexity, _grown(rule.convexity_mm, rule.convexity_allowance, face_width))
            difference = Measured(sec.leg_base.value - sec.leg_stem.value,
                                  math.hypot(sec.leg_base.sigma, sec.leg_stem.sigma))
            f.add(None, "leg_asymmetry_mm", difference,
                  _grown(rule.leg_asymmetry_mm, rule.leg_asymmetry_allowance, sec.throat.value), True)
            f.toe(sec.base_toe, "base", rule)
            f.toe(sec.stem_toe, "stem", rule)
        verdicts.append(f.verdict(measured))
    return _weld_verdict(verdicts, rule)
