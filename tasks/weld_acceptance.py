"""The measured weld judged against its acceptance limits (``schemas.acceptance``): each section
passes or fails, failing sections located (weld line, toe, position along the line), the weld as
a whole. A figure is judged on its measured value (its 1-sigma is reported beside it, not used);
a section or toe that could not be measured is listed as such, never passed."""

from __future__ import annotations

import math
from dataclasses import dataclass

from schemas.acceptance import AcceptanceRule, FigureLimits
from tasks.weld_fits import Measured
from tasks.weld_geometry import SectionMeasurement

__all__ = ["Violation", "SectionVerdict", "WeldVerdict", "judge_weld"]


@dataclass(frozen=True)
class Violation:
    line: str
    position_mm: float
    toe: str | None  # "minus" / "plus", None for a section figure
    figure: str
    value: float | None
    limit: str  # e.g. ">= 0.2", "groove required"


@dataclass(frozen=True)
class SectionVerdict:
    line: str
    position_mm: float
    measured: bool
    passed: bool
    violations: list[Violation]


@dataclass(frozen=True)
class WeldVerdict:
    passed: bool
    sections: list[SectionVerdict]
    n_measured: int
    n_failing: int
    n_not_measured: int
    failing_fraction: float
    max_failing_fraction: float


def _check(limits: FigureLimits, value: Measured, magnitude: bool = False) -> str | None:
    v = value.value
    if not math.isfinite(v):
        return None
    v = abs(v) if magnitude else v
    if limits.min is not None and v < limits.min:
        return f">= {limits.min:g}"
    if limits.max is not None and v > limits.max:
        return f"<= {limits.max:g}"
    return None


def judge_weld(sections: list[SectionMeasurement], rule: AcceptanceRule) -> WeldVerdict:
    verdicts = []
    for sec in sections:
        found: list[Violation] = []

        def add(toe, figure, value: Measured, limits: FigureLimits, magnitude=False):
            why = _check(limits, value, magnitude)
            if why:
                found.append(Violation(sec.line, sec.position_mm, toe, figure,
                                       round(float(value.value), 4), why + (" (magnitude)" if magnitude else "")))

        measured = all(t is not None for t in sec.toes) and math.isfinite(sec.height.value)
        if measured:
            add(None, "reinforcement_height_mm", sec.height, rule.reinforcement_height_mm)
            add(None, "reinforcement_width_mm", sec.width, rule.reinforcement_width_mm)
            add(None, "axial_misalignment_mm", sec.axial_misalignment, rule.axial_misalignment_mm, True)
            add(None, "angular_misalignment_deg", sec.angular_misalignment_deg, rule.angular_misalignment_deg, True)
            for toe in sec.toes:
                add(toe.side, "toe_radius_mm", toe.radius, rule.toe_radius_mm)
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
        verdicts.append(SectionVerdict(sec.line, sec.position_mm, measured, measured and not found, found))
    n_measured = sum(v.measured for v in verdicts)
    n_failing = sum(v.measured and not v.passed for v in verdicts)
    fraction = n_failing / n_measured if n_measured else 1.0
    return WeldVerdict(passed=n_measured > 0 and fraction <= rule.max_failing_fraction, sections=verdicts,
                       n_measured=n_measured, n_failing=n_failing, n_not_measured=len(verdicts) - n_measured,
                       failing_fraction=fraction, max_failing_fraction=rule.max_failing_fraction)
