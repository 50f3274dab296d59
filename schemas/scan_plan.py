"""A scan plan (``weldrecon plan``): what the planner was asked for, the passes and stickers it
chose, and what it predicts they will see. ``plan.json`` in a plan folder; ``weldrecon simulate
--plan`` scans it in the simulated cell. Lengths in mm, angles in degrees, times in s; poses are
``T_world_sensor`` (the scanner's frame in the cell, the robot's TCP) relative to the part's
nominal placement on the fixture, as the manifest's nominal motions are."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from schemas.common import Pose4x4, StrictModel, Vector3
from schemas.simulation import SimulationConfig

__all__ = ["PLAN_SCHEMA_VERSION", "ReachModel", "PlanRequirements", "PlanPass", "PlanSticker", "PlanOverlap",
           "FaceCoverage", "ToeCoverage", "SetupLink", "ScanPlan"]

PLAN_SCHEMA_VERSION = 1


class ReachModel(StrictModel):
    """The robot's reach, simply: the TCP (the scanner's origin) stays inside a box of the cell's
    frame (z up from the fixture's base plate) over every pass, and the scanner's view leans at
    most ``max_tilt_deg`` from straight down."""

    workspace_min_mm: Vector3 = (-700.0, -500.0, 50.0)
    workspace_max_mm: Vector3 = (700.0, 500.0, 600.0)
    max_tilt_deg: float = Field(default=65.0, ge=0, le=90)

    @model_validator(mode="after")
    def _possible(self) -> "ReachModel":
        if any(lo >= hi for lo, hi in zip(self.workspace_min_mm, self.workspace_max_mm)):
            raise ValueError("workspace_min_mm must be below workspace_max_mm on every axis")
        return self


class PlanRequirements(StrictModel):
    """What the plan must achieve. The scanner, the robot's speed and profile spacing (full
    resolution), the stickers' size and rules come with the part (``SimulationConfig``)."""

    setups: list[Literal["top", "bottom"]] = Field(default=["top", "bottom"], min_length=1)
    toe_coverage: float = Field(default=0.98, ge=0, le=1, description=(
        "share of every weld toe (stations 2 mm apart) measured at full resolution from both sides: "
        "by a pass whose laser comes from over the plate and by one from over the weld, each leaning "
        "10 deg or more across the toe; a fillet's toe (where the stem hides the side over the weld) "
        "by two passes whose rays lean across it at least 20 deg apart"))
    toe_incidence_limit_deg: float = Field(default=60.0, gt=0, lt=90, description=(
        "largest angle between a laser ray and the plate's normal at a toe that counts (a stem's "
        "normal at a stem toe)"))
    face_coverage: float = Field(default=0.95, ge=0, le=1, description=(
        "share of each face of the part (2 mm cells) some pass sees, both setups together"))
    plate_spacing_mm: float | None = Field(default=None, gt=0, description=(
        "coarsest point spacing across the scan line allowed off the weld zone; None: the scanner's own "
        "at its reference distance (full resolution everywhere)"))
    placement_tolerance_mm: float = Field(default=1.0, ge=0, le=20, description=(
        "how far the part may lie off its nominal place on the fixture (against its stops), each way"))
    placement_yaw_deg: float = Field(default=0.2, ge=0, le=5)
    sticker_tolerance_mm: float = Field(default=0.5, ge=0, le=5, description="how far a hand puts a sticker off its mark")
    extra_stickers_per_1000mm2: float = Field(default=0.5, ge=0, le=10, description=(
        "stickers beyond those the overlaps and the setups need, at random over the surface the passes "
        "see where stickers may go: more targets per pass, each pass's pose better held (the demo part, "
        "worst pass against the truth: 15.7 um with none, 13.8 with 0.25, 13.1 with 0.5; simulated with "
        "another seed 14.1, 11.1 and 7.6)"))
    min_setup_stickers: int = Field(default=6, ge=3, le=100, description=(
        "stickers the setups must share, seen whole from both, not in a line (registration.min_setup_targets "
        "and a margin against ambiguity)"))
    reach: ReachModel = ReachModel()


class PlanPass(StrictModel):
    pass_id: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
    setup: Literal["top", "bottom"]
    purpose: Literal["face", "side", "end", "weld"]
    direction: str = Field(description="a label for people, as the manifest's")
    T_world_sensor_start: Pose4x4
    travel_world: Vector3
    length_mm: float = Field(gt=0)
    speed_mm_s: float = Field(gt=0)
    profile_rate_hz: float = Field(gt=0)
    standoff_mm: float = Field(gt=0)
    tilt_deg: float = Field(description="the view's lean along the travel, from straight down")
    roll_deg: float = Field(description="the view's lean across the travel, from straight down")

    @property
    def duration_s(self) -> float:
        return self.length_mm / self.speed_mm_s


class PlanSticker(StrictModel):
    sticker_id: int = Field(ge=0)
    face: str
    centre_mm: Vector3 = Field(description="specimen frame, on the surface")
    normal: Vector3


class PlanOverlap(StrictModel):
    pass_a: str
    pass_b: str
    sticker_ids: list[int] = Field(description="stickers both passes see whole, at every placement within tolerance")
    spread_mm: float = Field(description="their largest distance off their best line")


class SetupLink(StrictModel):
    setups: tuple[str, str]
    sticker_ids: list[int]
    spread_mm: float


class FaceCoverage(StrictModel):
    face: str
    area_mm2: float
    seen: float = Field(description="share of its 2 mm cells some pass sees")
    passes_median: float = Field(description="median number of passes that see a seen cell")


class ToeCoverage(StrictModel):
    toe: str
    rule: Literal["both sides", "two directions"] = Field(default="both sides", description=(
        "both sides: a butt weld's toe, lit from over the plate and from over the weld, each leaning 10 deg "
        "or more across it; two directions: a fillet's toe (the stem hides the side over the weld), lit by "
        "rays leaning across it at least 20 deg apart"))
    length_mm: float
    stations: int
    plate_side: float = Field(description=(
        "both sides: share of stations seen by a laser from over the plate; two directions: seen at all"))
    weld_side: float = Field(description=(
        "both sides: share of stations seen by a laser from over the weld; two directions: seen from a "
        "second direction 20 deg from the first"))
    both_sides: float = Field(description="share of stations measured as the rule asks")


class ScanPlan(StrictModel):
    schema_version: Literal[1] = PLAN_SCHEMA_VERSION
    part: SimulationConfig = Field(description="the part, the cell's scanner, robot and fixture (the plan's own "
                                               "``plan`` field is not used)")
    requirements: PlanRequirements
    passes: list[PlanPass]
    stickers: list[PlanSticker]
    overlaps: list[PlanOverlap]
    setup_links: list[SetupLink]
    faces: list[FaceCoverage]
    toes: list[ToeCoverage]
    no_sticker_x_mm: tuple[float, float] = Field(description=(
        "the weld zone and its clearance across the part's faces, specimen x: no sticker goes there"))
    scan_time_s: float
    candidates_tried: int = Field(description="plans the search checked before this one, the fastest that met "
                                              "every requirement")
