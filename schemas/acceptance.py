"""Acceptance limits of the measured weld, per joint and treatment (``data_catalog/weld_acceptance.yaml``
holds the defaults and their sources). A section passes when every figure it measured lies within
its rule's limits; the weld passes when at most ``max_failing_fraction`` of its sections fail.
A figure within ``uncertain_sigmas`` of its 1-sigma of a limit is "uncertain" (its section listed
as such, not failed): the measurement cannot tell on which side of the limit it lies."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator, model_validator

from schemas.common import InputModel

__all__ = ["FigureLimits", "Allowance", "AcceptanceRule", "AcceptanceLimits", "LIMITED_FIGURES"]

Treatment = Literal["as-welded", "hfmi-treated", "burr-ground"]

# the figures a rule may limit: per toe (toe radius, flank angle, undercut, the groove's) or per
# section (height, width, misalignment, taken by magnitude)
LIMITED_FIGURES = ("toe_radius_mm", "flank_angle_deg", "undercut_depth_mm", "groove_depth_mm", "groove_width_mm",
                   "groove_radius_mm", "reinforcement_height_mm", "reinforcement_width_mm", "axial_misalignment_mm",
                   "angular_misalignment_deg")
# a fillet weld's document figures whose limit is a field of another name: both legs, one limit
_RULE_FIELD = {"leg_base_mm": "leg_length_mm", "leg_stem_mm": "leg_length_mm"}


class FigureLimits(InputModel):
    """Inclusive bounds of one figure, in its unit; None: not limited on that side."""

    min: float | None = Field(default=None, ge=0)
    max: float | None = Field(default=None, ge=0)

    @model_validator(mode="after")
    def _ordered(self) -> "FigureLimits":
        if self.min is not None and self.max is not None and self.min > self.max:
            raise ValueError(f"min {self.min} is above max {self.max}")
        return self


class Allowance(InputModel):
    """A limit that grows with the weld's size, as ISO 5817 writes many: ``base_mm`` + ``per_mm`` x
    a size of the section (mm)."""

    base_mm: float = Field(ge=0)
    per_mm: float = Field(ge=0)

    def at(self, size_mm: float) -> float:
        return self.base_mm + self.per_mm * size_mm


class AcceptanceRule(InputModel):
    joint: str = Field(min_length=1, description="the manifest's weld.joint, e.g. 'double-sided butt'")
    treatment: Treatment
    source: str = Field(min_length=1, description="where the limits come from, in words")
    toe_radius_mm: FigureLimits = FigureLimits()
    flank_angle_deg: FigureLimits = FigureLimits()
    undercut_depth_mm: FigureLimits = FigureLimits()
    groove_depth_mm: FigureLimits = FigureLimits()
    groove_width_mm: FigureLimits = FigureLimits()
    groove_radius_mm: FigureLimits = FigureLimits()
    reinforcement_height_mm: FigureLimits = FigureLimits()
    reinforcement_width_mm: FigureLimits = FigureLimits()
    axial_misalignment_mm: FigureLimits = FigureLimits()
    angular_misalignment_deg: FigureLimits = FigureLimits()
    leg_length_mm: FigureLimits = FigureLimits()  # fillet welds: each leg
    throat_mm: FigureLimits = FigureLimits()
    convexity_mm: FigureLimits = FigureLimits()
    leg_asymmetry_mm: FigureLimits = FigureLimits()  # |base leg - stem leg|
    convexity_allowance: Allowance | None = Field(default=None, description=(
        "a fillet's convexity at most this x the section's face width b (between its toes), within convexity_mm"))
    leg_asymmetry_allowance: Allowance | None = Field(default=None, description=(
        "a fillet's legs' difference at most this x the section's measured throat a, within leg_asymmetry_mm"))
    toe_within_groove: bool = Field(default=False, description="every toe must lie fully within its groove")
    groove_required: bool = Field(default=False, description="a toe without a measured groove fails")
    max_failing_fraction: float = Field(default=0.0, ge=0, le=1, description=(
        "the weld passes when at most this share of its measured sections fail"))
    uncertain_sigmas: float = Field(default=1.0, ge=0, le=10, description=(
        "a figure whose measured value lies within this many of its 1-sigma of a limit (on either "
        "side) is 'uncertain' there: listed for a person to look at, neither failed nor passed "
        "silently; the weld passes when no section fails for certain (0: the value alone decides)"))

    def limits(self, figure: str) -> FigureLimits:
        """The limits of a weld document's figure (a toe's, a section's or a fillet's, by its name)."""
        return getattr(self, _RULE_FIELD.get(figure, figure))

    @field_validator("flank_angle_deg", "angular_misalignment_deg")
    @classmethod
    def _angle(cls, value: FigureLimits) -> FigureLimits:
        for bound in (value.min, value.max):
            if bound is not None and bound > 90:
                raise ValueError(f"an angle limit must lie within [0, 90] degrees, got {bound}")
        return value


class AcceptanceLimits(InputModel):
    schema_version: Literal["1.0"] = "1.0"
    rules: list[AcceptanceRule] = Field(min_length=1)

    @field_validator("rules")
    @classmethod
    def _one_rule_each(cls, value: list[AcceptanceRule]) -> list[AcceptanceRule]:
        seen = [(r.joint, r.treatment) for r in value]
        twice = sorted({k for k in seen if seen.count(k) > 1})
        if twice:
            raise ValueError(f"one rule per joint and treatment, repeated: {twice}")
        return value

    def rule_for(self, joint: str, treatment: str) -> AcceptanceRule | None:
        for r in self.rules:
            if r.joint == joint and r.treatment == treatment:
                return r
        return None
