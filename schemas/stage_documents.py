"""The JSON documents the stages write besides their arrays: the registration's and the
refinement's summaries (``registration.json``, ``refine.json``), the FE model's (``volume.json``),
the consistency checks and the sample's report (``report.json``). Each is written and read only
through its model (``flows/stages/outputs.py``); the weld's is ``schemas.weld_document``.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import ConfigDict, Field, SerializerFunctionWrapHandler, model_serializer

from schemas.common import StrictModel, without_none
from schemas.provenance import StageName
from schemas.weld_document import FigureStatistics, Finding, ToeSide, WeldLineFound

__all__ = ["PassPair", "SetupEvidence", "RegistrationSummary", "SurfacePair", "SurfaceMatch", "RefineSummary",
           "SolidChecks", "QualityStatistics", "ElementQuality", "VolumeSets", "FEModelSummary", "Check",
           "WeldReport", "Report", "STAGE_NAME"]

STAGE_NAME = StageName


# --- registration.json ---
class PassPair(StrictModel):
    a: str
    b: str
    common_targets: int


class MeasuredTurn(StrictModel):
    """How the part was turned between two setups, from the registered stickers (tasks.graph.setup_turn):
    a screw about the line through ``axis_point_mm`` (its point nearest the calibrated axis point)
    along ``axis_direction`` (cell frame), by ``angle_deg``, sliding ``slide_mm`` along it."""

    axis_point_mm: tuple[float, float, float]
    axis_direction: tuple[float, float, float]
    angle_deg: float
    slide_mm: float


class SetupEvidence(StrictModel):
    """Why a turned setup's match is no chance agreement: the targets it brought together against
    the most a clearly different transform did. A setup turned by a positioner (``prior``) is
    matched on the positioner's calibrated turn: ``prior_difference_deg`` and ``_mm`` say how far
    the stickers' own match lies from it, ``turn`` the turn the stickers give (the axis's
    calibration, checked)."""

    a: str
    b: str
    targets: int
    runner_up: int
    prior: Literal["positioner"] | None = None
    prior_difference_deg: float | None = None
    prior_difference_mm: float | None = None
    turn: MeasuredTurn | None = None

    @model_serializer(mode="wrap")
    def _turned_by_hand_unsaid(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        """Written as before positioners for a setup turned by hand."""
        return without_none(handler(self), "prior", "prior_difference_deg", "prior_difference_mm", "turn")


class RegistrationSummary(StrictModel):
    schema_version: Literal["1"] = "1"
    method: str | None = None  # set where no target registration ran (a sample registered on its surfaces)
    pairs: list[PassPair]
    pairs_below_min_common: list[PassPair]
    pass_rms_mm: dict[str, float | None]
    between_setups: list[SetupEvidence]


# --- refine.json ---
class SurfacePair(StrictModel):
    a: str
    b: str
    points: int
    rms_mm: float | None


class SurfaceMatch(StrictModel):
    """A pair of scans tried by the global surface registration."""

    a: str
    b: str
    accepted: bool
    reason: str
    fitness: float
    rms_mm: float | None
    runner_up_fitness: float
    matches: int


class RefineSummary(StrictModel):
    schema_version: Literal["1"] = "1"
    method: str | None = None  # a sample registered on its surfaces: how
    surface_pairs: list[SurfacePair]
    step_mm: list[float]
    pairs: list[SurfaceMatch] | None = None  # the global surface registration's pairs
    tree: list[tuple[str, str]] | None = None  # the pairs that chained the scans together


# --- volume.json ---
class SolidChecks(StrictModel):
    tetrahedra: int
    nodes: int
    boundary_faces: int
    weld_zone_faces: int
    components: int
    negative_or_flat: int
    open_boundary_edges: int
    volume_mm3: float
    surface_volume_mm3: float
    volume_difference: float | None  # None: a surface of no volume


class QualityStatistics(StrictModel):
    worst: float
    p1: float
    median: float
    p99: float


class ElementQuality(StrictModel):
    """The figures an FE analyst asks for (the per-element values are the volume stage's arrays)."""

    min_dihedral_deg: QualityStatistics
    aspect_ratio: QualityStatistics
    below_10_deg: int


class VolumeSets(StrictModel):
    elements: str
    weld_zone_nodes: str
    weld_zone_surface: str


class FEModelSummary(StrictModel):
    """``volume.json``: the FE model made (with its checks and quality), or why not."""

    schema_version: Literal["1"] = "1"
    made: bool
    why: str | None = None
    surface_triangles: int | None = None
    meshed_triangles: int | None = None
    surface_remeshed: bool | None = None
    surface_kept_because: str | None = None  # gmsh's message where it could not remesh the surface
    element_type: Literal["C3D4", "C3D10"] | None = None  # the .inp's (C3D10: the VTU's tetra10)
    model_nodes: int | None = None  # the .inp's nodes: the corners (solid.nodes) and C3D10's edge nodes
    slivers_peeled: int | None = None  # flat elements on the surface removed (tasks.sliver_repair)
    short_edges_collapsed: int | None = None  # the surface's short edges collapsed (tasks.sliver_repair)
    nodes_moved: int | None = None  # nodes moved to mend poor elements (tasks.sliver_repair)
    solid: SolidChecks | None = None
    quality: ElementQuality | None = None
    weld_lines: int | None = None
    toe_lines: int | None = None
    toe_points: int | None = None
    sets: VolumeSets | None = None


# --- stage stress ---
class ToeStress(StrictModel):
    """One toe in one section: the highest maximum principal stress on the outline within reach
    of the measured toe over the nominal stress (the force over its plate's measured thickness)."""

    line: str  # the weld line the toe belongs to
    side: ToeSide
    factor: float | None  # None: no outline node within reach
    peak_mpa: float | None
    nominal_mpa: float | None  # None: no plate measured in the toe's plate window
    plate_thickness_mm: float | None
    toe_specimen_mm: tuple[float, float, float]  # the measured toe where the section crosses it
    peak_specimen_mm: tuple[float, float, float] | None  # where the peak is
    toe_radius_mm: float | None = None  # the weld stage's measured toe radius in the nearest section (None: not measured)
    notch_factor: float | None = None  # the same section with its notches rounded to the IIW reference radius (stress.notch_stress)


class StressSection(StrictModel):
    """One 2-D section model: where it is, its size and its checks."""

    position_mm: float  # along the driving weld line (the weld stage's position)
    origin_specimen_mm: tuple[float, float, float]
    nodes: int
    elements: int
    force_n_per_mm: float  # the force through it, per mm of the weld's length (bent: the net force, ~0)
    imbalance: float  # |held + pulled| / pulled reaction (bent: the ends' moments about one point)
    # the membrane stress in the plate windows against force / thickness, relative (the larger); bent: the
    # bending stress at the surface against 6 M / t^2, or the membrane part over it, whichever is larger
    membrane_error: float | None
    toes: list[ToeStress]


class ToeHotSpot(StrictModel):
    """A toe line's highest section: the predicted crack start."""

    line: str
    side: ToeSide
    position_mm: float
    factor: float
    at_specimen_mm: tuple[float, float, float]
    sections: int
    median_factor: float


class StressConvergence(StrictModel):
    """The hot spot's section again with elements half the size at the toes."""

    position_mm: float
    line: str
    side: ToeSide
    toe_size_mm: float
    factor: float
    finer_factor: float
    change: float  # finer / default - 1


class DrawnToe(StrictModel):
    """A toe of the drawn weld: its factor with the toe rounded to the notch radius."""

    line: str
    side: ToeSide
    factor: float | None  # None: no outline node within reach
    at_section_mm: tuple[float, float]  # the drawn toe in the section (x across, y up; mm)


class DrawnStress(StrictModel):
    """The same computation on the drawn (idealised) weld: the manifest's plate, straight and
    aligned, each face's cap a circular segment of the median measured width and height, the toes
    rounded to ``notch_radius_mm`` (a drawn toe is a sharp corner, whose stress has no finite peak).
    A T-joint's: its base and stem as the manifest gives them, each fillet's face straight between
    its median measured legs (``legs``), the toes rounded the same way."""

    made: bool
    why: str | None = None
    thickness_mm: float | None = None
    notch_radius_mm: float | None = None
    caps: dict[str, tuple[float, float]] = {}  # face ("top", "bottom") -> (width, height), mm
    legs: dict[str, tuple[float, float]] | None = None  # a T-joint's: weld line -> (leg on the base, on the stem), mm
    toes: list[DrawnToe] = []


class FatigueEstimate(StrictModel):
    """A toe line's fatigue life by the IIW effective notch stress method at its notch hot spot:
    cycles = 2e6 (FAT / notch stress range)^slope (constant amplitude; beyond 1e7 cycles the
    slope is 22)."""

    line: str
    side: ToeSide
    position_mm: float
    notch_factor: float
    nominal_range_mpa: float
    notch_range_mpa: float
    fat_mpa: float
    slope: float
    cycles: float


class StressFigures(StrictModel):
    """What ``stress.json`` and the report's ``stress`` both hold: whether made (or why not), the hot
    spots, the checks, the notch stress, fatigue, drawn weld and resolution."""

    made: bool
    why: str | None = None
    model: str | None = None  # in words: element, plane, load, ends
    hot_spots: list[ToeHotSpot] = []
    hot_spot: ToeHotSpot | None = None  # the highest of all
    convergence: StressConvergence | None = None
    convergence_refused: str | None = None  # why the hot spot's finer section gave no figure (None: it did, or no hot spot)
    max_imbalance: float | None = None
    max_membrane_error: float | None = None
    notch_radius_mm: float | None = None  # None: no notch stress (stress.notch_stress off)
    notch_hot_spots: list[ToeHotSpot] = []  # each toe line's highest notch factor
    fatigue: list[FatigueEstimate] = []
    fatigue_basis: str | None = None  # the method, class and assumptions; or why there is no estimate
    drawn: DrawnStress | None = None
    point_spacing_mm: float | None = None  # the measured points' median spacing in the sections' slabs
    toes_finer_than_points: int | None = None  # toes whose measured radius is under the point spacing


class RefusedSection(StrictModel):
    """A section CalculiX refused (``tasks.section_model.each_solved``): left out of the stress."""

    position_mm: float
    why: str


class StressSummary(StressFigures):
    """``stress.json``: the stress concentration along every measured toe, or why not computed."""

    schema_version: Literal["1"] = "1"
    driving_line: str | None = None
    sections: list[StressSection] = []
    sections_refused: list[RefusedSection] = []


class StressReport(StressFigures):
    """The stress's part of the report: the hot spots and the checks (each section's figures stay
    in the stress stage's stress.json)."""

    sections: int = 0


# --- report.json ---
class Check(StrictModel):
    """One consistency check of the run: ``result`` "ok" or "flagged", ``what`` in words."""

    check: str
    pass_: str = Field(alias="pass")  # the pass it concerns, or "all"
    result: Literal["ok", "flagged"]
    what: str
    measured: Any = None

    model_config = ConfigDict(**StrictModel.model_config, populate_by_name=True)


class WeldReport(StrictModel):
    """The weld's part of the report (the per-section values stay in ``weld_geometry.json``)."""

    measured: bool
    why_not: str | None = None
    joint: str | None = None
    treatment: str | None = None
    acceptance_source: str | None = None
    acceptance_rule_source: str | None = None
    sections: int | None = None
    sections_measured: int | None = None
    sections_not_measured: int | None = None
    failing: int | None = None
    sections_uncertain: int | None = None
    passed: bool | None = None
    verdict: str | None = None
    lines_without_sections: list[str] = []
    failing_sections: list[Finding] = []
    uncertain_sections: list[Finding] = []
    lines: list[WeldLineFound] = []
    statistics: dict[str, FigureStatistics] = {}


class Report(StrictModel):
    """``report.json``: a function of the stages' outputs and records only (no times, no paths,
    no cache flags: those are in the audit trail), so the same inputs give the same bytes."""

    schema_version: Literal["1"] = "1"
    sample_id: str
    passes: list[str]
    config: dict[str, Any]
    stages: dict[STAGE_NAME, Any]  # what each stage measured (per pass: a list)
    registration: RegistrationSummary
    refinement: RefineSummary
    registration_method: dict[str, str]  # per pass: "targets", "surfaces from given poses", ...
    mesh: dict[str, Any]
    volume_mesh: FEModelSummary
    stress: StressReport
    weld: WeldReport
    checks: list[Check]
    deliverables: dict[str, str]  # results/ file name -> sha256
    stage_keys: dict[STAGE_NAME, str | list[str]]
