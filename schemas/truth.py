"""Ground truth written by the simulator beside a sample; the pipeline never reads it."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field, SerializerFunctionWrapHandler, model_serializer

from schemas.common import Pose4x4, StrictModel, Vector3, without_none

__all__ = ["TRUTH_SCHEMA_VERSION", "PointLabel", "Material", "TrueSticker", "WeldSection",
           "TruePass", "GroundTruth", "WeldSectionDetail", "WeldTruth", "TrueToeLine", "TrueToeLines"]

TRUTH_SCHEMA_VERSION = "1.0"


class PointLabel:
    """Per-point label of a simulated pass (``labels`` array of the truth store)."""

    VALID = 0
    SHADOW = 1  # the laser hit the surface but the camera could not see the spot
    DROPOUT = 2  # the sensor lost a visible spot (reflective or random)
    NO_SURFACE = 3  # no surface within the measuring range along the laser ray
    GRAZING = 4  # surface too steep to the laser or the camera to return a peak
    OUTLIER = 5  # a spurious peak: reported, but away from the surface


class Material:
    """Per-point surface material (``materials`` array of the truth store)."""

    NONE = 0
    STEEL = 1  # sprayed steel
    GROUND = 2  # burr-ground, reflective
    STICKER = 3
    FIXTURE = 4
    FIXTURE_STICKER = 5


class TrueSticker(StrictModel):
    sticker_id: int
    on: Literal["specimen", "fixture"]
    face: str
    centre_mm: Vector3 = Field(description="specimen frame if on the specimen, world frame if on the fixture")
    normal: Vector3
    diameter_mm: float


class WeldSection(StrictModel):
    """The weld cap's true parameters at one position along the weld (specimen frame)."""

    side: Literal["top", "bottom"]
    y_mm: float
    centre_x_mm: float
    height_mm: float
    width_mm: float
    flank_angle_deg: tuple[float, float]
    toe_radius_mm: tuple[float, float]
    undercut_depth_mm: tuple[float, float]


class TruePass(StrictModel):
    pass_id: str
    setup: str
    T_nominal_true: Pose4x4 = Field(description="the pass's rigid robot error, world frame")
    n_points: int
    label_counts: dict[str, int]


class TruePositioner(StrictModel):
    """The positioner's true turn between two setups: ``setup`` is ``from_setup`` turned
    ``angle_deg`` about the line through ``axis_point_mm`` along ``axis_direction`` (cell frame)."""

    from_setup: str
    setup: str
    axis_point_mm: Vector3
    axis_direction: Vector3
    angle_deg: float


class GroundTruth(StrictModel):
    schema_version: Literal["1.0"] = TRUTH_SCHEMA_VERSION
    sample_id: str
    seed: int
    preset: str
    T_world_specimen: dict[str, Pose4x4] = Field(description="per setup")
    stickers: list[TrueSticker]
    weld_sections: list[WeldSection]
    misalignment: dict[str, float]
    passes: list[TruePass]
    overlapping_pairs: list[tuple[str, str]]
    common_stickers: dict[str, list[int]] = Field(description="'A|B' -> sticker ids both passes see whole")
    positioner: "TruePositioner | None" = Field(default=None, description="the positioner's true turn, if it turned the part")

    @model_serializer(mode="wrap")
    def _turned_by_hand_unsaid(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        """Written as before positioners when the part was turned by hand."""
        return without_none(handler(self), "positioner")


class WeldSectionDetail(StrictModel):
    """The drawn weld cap at one position along the weld, specimen frame: the figures a section
    measures. Pairs are (toe at -x, toe at +x). ``peak_height_mm``: the highest point of the
    drawn face over the line between the plates' surfaces at the drawn toes (bead ripple and the plates' misalignment
    under the cap included; ``cap_height_mm`` is the cap alone, without either).
    Groove figures (HFMI or burr-ground) are None on an as-welded cap: ``groove_width_mm`` is the
    chord at plate level, ``groove_radius_mm`` the imprint's circle."""

    side: Literal["top", "bottom"]
    y_mm: float
    centre_x_mm: float
    cap_height_mm: float
    peak_height_mm: float
    width_mm: float
    flank_angle_deg: tuple[float, float]
    toe_radius_mm: tuple[float, float]
    undercut_depth_mm: tuple[float, float]
    groove_depth_mm: tuple[float, float] | None
    groove_width_mm: tuple[float, float] | None
    groove_radius_mm: tuple[float, float] | None
    toe_within_groove: tuple[bool, bool] | None


class WeldTruth(StrictModel):
    """``truth/weld_sections.json``: the drawn weld, section by section (every ``step_mm``), and the
    plates' misalignment (the +x plate higher by ``axial_misalignment_mm`` at the weld's centre
    and tilted by ``angular_misalignment_deg``)."""

    schema_version: Literal["1.0"] = "1.0"
    treatment: str
    step_mm: float
    axial_misalignment_mm: float
    angular_misalignment_deg: float
    sections: list[WeldSectionDetail]


class FilletSectionTruth(StrictModel):
    """A T-joint's fillet weld as drawn at one station ``y_mm``: its legs along the base and up
    the stem from the root (to the corners the toes' roundings replace), the toe angles (the
    face's tangent at each corner against its plate), the toe radii, the face's largest rise
    above the legs' chord (convexity) and the throat (the root's height over that chord)."""

    weld: str = Field(description="the manifest's weld line (the root)")
    y_mm: float
    leg_base_mm: float
    leg_stem_mm: float
    toe_angle_deg: tuple[float, float] = Field(description="base toe, stem toe")
    face_angle_deg: tuple[float, float] = Field(description=(
        "base toe, stem toe: the face's direction against its plate where it starts after the toe's "
        "rounding (the rounding is tangent to the corner's tangent line; a convex face has turned "
        "away from it by then)"))
    toe_radius_mm: tuple[float, float] = Field(description="base toe, stem toe")
    convexity_mm: float
    throat_mm: float


class FilletWeldTruth(StrictModel):
    """``truth/fillet_weld.json``: a T-joint's fillet welds as drawn every ``step_mm``."""

    schema_version: Literal["1.0"] = "1.0"
    step_mm: float
    sections: list[FilletSectionTruth]


class TrueToeLine(StrictModel):
    """One weld toe as it was drawn: a polyline along the weld (specimen frame, mm), where the weld's
    face meets the plate (the middle of the toe's rounding)."""

    name: str
    weld: str = Field(description="the manifest's weld line the toe belongs to")
    plate: Literal["base", "stem"]
    points_mm: list[Vector3] = Field(min_length=2)


class TrueToeLines(StrictModel):
    """``truth/toes.json``: the true toe lines of a simulated fillet-welded part."""

    schema_version: Literal["1.0"] = "1.0"
    sample_id: str
    toes: list[TrueToeLine]
