"""The weld stage's document, ``weld_geometry.json``: every section's figures with their 1-sigma,
the verdict against the acceptance limits, the statistics along the weld. Written and read only
through these models (``flows/stages/outputs.py``: ``WELD_GEOMETRY``); a renamed field is a
validation error where the file is read, not a missing key deep in a consumer.

Frames: ``centre_specimen_mm``, ``face_normal`` and ``across`` are in the specimen frame (the
frame of the manifest's weld lines, placed by ``flows.stages.frames.weld_frame``); positions along
a line are from the line's first point, mm. A figure the fits could not determine is ``None``.

A butt weld's sections are ``WeldSection`` (toes ``minus`` and ``plus`` across the weld); a fillet
weld's (a T-joint's or a cruciform's, ``tasks.fillet_section``) are ``FilletWeldSection`` (toes
``base`` and ``stem``, on the plate each stands on; legs, throat, convexity).
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from schemas.acceptance import AcceptanceRule
from schemas.common import StrictModel

__all__ = ["Figure", "GrooveFigures", "ToeFigures", "SectionToes", "FilletToes", "Finding", "WeldSection",
           "FilletWeldSection", "WeldLineFound", "SectionWhere", "FigureStatistics", "WeldSummary", "WeldGeometry",
           "TOE_SIDES", "FILLET_TOE_SIDES", "TOE_FIGURES", "SECTION_FIGURES", "FILLET_SECTION_FIGURES"]

TOE_SIDES = ("minus", "plus")
FILLET_TOE_SIDES = ("base", "stem")
ToeSide = Literal["minus", "plus", "base", "stem"]
# the figures measured per toe and per section, as named in the document and in the acceptance rules
TOE_FIGURES = ("toe_radius_mm", "flank_angle_deg", "undercut_depth_mm", "groove_depth_mm", "groove_width_mm",
               "groove_radius_mm")
SECTION_FIGURES = ("reinforcement_height_mm", "reinforcement_width_mm", "axial_misalignment_mm",
                   "angular_misalignment_deg")
FILLET_SECTION_FIGURES = ("leg_base_mm", "leg_stem_mm", "throat_mm", "convexity_mm")


class Figure(StrictModel):
    """A measured figure and its 1-sigma, in the unit its field names; None: not determined."""

    value: float | None
    sigma: float | None


class GrooveFigures(StrictModel):
    """The HFMI groove at a treated toe."""

    depth_mm: Figure  # below the plate
    width_mm: Figure  # chord at plate level
    radius_mm: Figure  # the imprint's radius
    toe_within_groove: bool
    fit_rms_mm: float
    points: int


class ToeFigures(StrictModel):
    side: ToeSide
    # where the flank meets the plate (or the groove): a butt weld's across the weld from the
    # section's centre, a fillet weld's along its plate from the root (the leg)
    position_u_mm: float
    position_sigma_mm: float | None
    flank_angle_deg: Figure
    toe_radius_mm: Figure = Field(description=(
        "the notch radius at the toe: the toe fillet's as welded, the groove's on a treated toe"))
    undercut_depth_mm: Figure
    fit_rms_mm: float
    points: int
    treated: bool
    groove: GrooveFigures | None = None
    note: str | None = None

    def figure(self, name: str) -> Figure | None:
        """One of ``TOE_FIGURES`` by name (the groove's None on an untreated toe)."""
        if name.startswith("groove_"):
            return None if self.groove is None else getattr(self.groove, name[len("groove_"):])
        return getattr(self, name)


class SectionToes(StrictModel):
    minus: ToeFigures | None
    plus: ToeFigures | None

    def sides(self) -> list[tuple[str, ToeFigures | None]]:
        return [("minus", self.minus), ("plus", self.plus)]

    def both(self) -> bool:
        return self.minus is not None and self.plus is not None


class FilletToes(StrictModel):
    """A fillet weld section's toes: on the base plate and on the stem."""

    base: ToeFigures | None
    stem: ToeFigures | None

    def sides(self) -> list[tuple[str, ToeFigures | None]]:
        return [("base", self.base), ("stem", self.stem)]

    def both(self) -> bool:
        return self.base is not None and self.stem is not None


class Finding(StrictModel):
    """A figure that breaks (``failing``) or straddles (``uncertain``) an acceptance limit."""

    line: str
    position_mm: float
    toe: ToeSide | None  # None: a section figure
    figure: str
    value: float | None
    limit: str  # e.g. ">= 0.2", "groove required", "not measured"
    sigma: float | None = None


class WeldSection(StrictModel):
    line: str
    position_mm: float
    centre_specimen_mm: tuple[float, float, float]
    points: int
    reinforcement_height_mm: Figure
    reinforcement_width_mm: Figure
    axial_misalignment_mm: Figure
    angular_misalignment_deg: Figure
    toes: SectionToes
    passed: bool | None  # None: no acceptance rule
    verdict: Literal["pass", "fail", "uncertain", "not measured"] | None
    violations: list[Finding]
    uncertain: list[Finding]
    note: str | None = None

    def figure(self, name: str) -> Figure:
        """One of ``SECTION_FIGURES`` by name."""
        return getattr(self, name)


class FilletWeldSection(StrictModel):
    """A fillet weld's section (``tasks.fillet_section``): ``centre_specimen_mm`` is its root (where
    the plates' fitted faces cross), ``base_direction`` the base plate's face outward from it and
    ``stem_direction`` the stem's face upward (unit, specimen frame), ``plates_angle_deg`` the angle
    between them; each toe's ``position_u_mm`` is its leg."""

    line: str
    position_mm: float
    centre_specimen_mm: tuple[float, float, float]
    points: int
    base_direction: tuple[float, float, float]
    stem_direction: tuple[float, float, float]
    plates_angle_deg: float | None
    leg_base_mm: Figure
    leg_stem_mm: Figure
    throat_mm: Figure
    convexity_mm: Figure
    toes: FilletToes
    passed: bool | None  # None: no acceptance rule
    verdict: Literal["pass", "fail", "uncertain", "not measured"] | None
    violations: list[Finding]
    uncertain: list[Finding]
    note: str | None = None

    def figure(self, name: str) -> Figure:
        """One of ``FILLET_SECTION_FIGURES`` by name."""
        return getattr(self, name)

    def toe_specimen_mm(self, side: str) -> tuple[float, float, float] | None:
        """Where the toe on ``side`` ("base" or "stem") is, specimen frame."""
        toe = getattr(self.toes, side)
        if toe is None:
            return None
        direction = self.base_direction if side == "base" else self.stem_direction
        return tuple(c + toe.position_u_mm * d for c, d in zip(self.centre_specimen_mm, direction))


class WeldLineFound(StrictModel):
    """A weld line as the sections found it on the data (specimen frame)."""

    name: str
    sections: int
    offset_mm: float  # the refined line's shift across the nominal one, at its middle
    turn_deg: float
    face_normal: tuple[float, float, float]
    across: tuple[float, float, float]
    measured_extent_mm: tuple[float, float]


class SectionWhere(StrictModel):
    line: str
    position_mm: float
    toe: ToeSide | None = None


class FigureStatistics(StrictModel):
    """One figure along the weld: NaN values not counted (``n`` 0: none measured, the rest None)."""

    n: int
    min: float | None = None
    p5: float | None = None
    median: float | None = None
    p95: float | None = None
    max: float | None = None
    min_at: SectionWhere | None = None
    max_at: SectionWhere | None = None


class WeldSummary(StrictModel):
    sections: int
    sections_measured: int | None  # None only in documents written before 2026-11-27 without a rule
    sections_not_measured: int | None
    failing: int | None  # None: no acceptance rule for the joint and treatment
    sections_uncertain: int | None
    passed: bool | None
    verdict: str  # "pass", "fail", or why there is no verdict (no rule; no weld found; a line not measured)
    lines_without_sections: list[str] = []  # weld lines that gave no measured section (not scanned, no weld there)


class WeldGeometry(StrictModel):
    """``weld_geometry.json``. ``measured`` False: ``why_not`` says why, the rest is empty."""

    schema_version: Literal["1"] = "1"
    measured: bool
    why_not: str | None = None
    joint: str | None
    treatment: str | None
    frame: str | None = None
    acceptance: AcceptanceRule | None = None
    acceptance_source: str | None = None
    lines: list[WeldLineFound] = []
    summary: WeldSummary | None = None
    statistics: dict[str, FigureStatistics] = {}
    failing: list[Finding] = []
    uncertain: list[Finding] = []
    sections: list[WeldSection | FilletWeldSection] = []

    def line(self, name: str) -> WeldLineFound:
        for line in self.lines:
            if line.name == name:
                return line
        raise KeyError(f"weld_geometry.json has no line {name!r} (it has {[l.name for l in self.lines]})")

    def line_names(self) -> list[str]:
        """The lines that have sections, in the order of their sections."""
        return list(dict.fromkeys(s.line for s in self.sections))
