"""Configuration of the simulated scanning cell: specimen, weld, stickers, fixture, robot,
line scanner and scan plan. All lengths in mm, angles in degrees, rates in Hz or per point."""

from __future__ import annotations

import math
from typing import Literal

from pydantic import Field, model_validator

from schemas.common import FloatRange, Pose4x4, StrictModel, Vector3

__all__ = [
    "SpecimenConfig",
    "WeldConfig",
    "StickerConfig",
    "FixtureConfig",
    "ScannerConfig",
    "RobotConfig",
    "WidthPass",
    "ScanPlanConfig",
    "PlacementConfig",
    "TrueMeshConfig",
    "TJointConfig",
    "SimulationConfig",
]


class SpecimenConfig(StrictModel):
    """Dog-bone plate: grips of ``grip_width_mm`` at both ends, a gauge section of
    ``gauge_width_mm`` over ``gauge_length_mm`` in the middle, joined by arcs of
    ``transition_radius_mm``; water-jet-cut side walls."""

    length_mm: float = Field(default=570.0, gt=0, le=2000)
    grip_width_mm: float = Field(default=100.0, gt=0, le=1000)
    gauge_width_mm: float = Field(default=70.0, gt=0, le=1000)
    gauge_length_mm: float = Field(default=180.0, ge=0, le=2000)
    transition_radius_mm: float = Field(default=80.0, gt=0, le=2000)
    thickness_mm: float = Field(default=20.0, gt=0, le=200)
    cut_roughness_mm: float = Field(default=0.04, ge=0, le=1, description="std of water-jet striations")
    cut_taper_mm: float = Field(default=0.05, ge=0, le=2, description="kerf taper over the thickness")

    @model_validator(mode="after")
    def _possible(self) -> "SpecimenConfig":
        if self.gauge_width_mm > self.grip_width_mm:
            raise ValueError("gauge_width_mm must not exceed grip_width_mm")
        if (self.grip_width_mm - self.gauge_width_mm) / 2 > self.transition_radius_mm:
            raise ValueError("transition_radius_mm must be at least half the width step (grip - gauge) / 2")
        if self.transition_length_mm() * 2 + self.gauge_length_mm >= self.length_mm:
            raise ValueError(
                "gauge_length_mm plus the two transitions must be shorter than length_mm "
                f"(transitions are {self.transition_length_mm():.1f} mm each)"
            )
        return self

    def transition_length_mm(self) -> float:
        """Length along x of one arc that narrows the grip to the gauge width."""
        drop = min((self.grip_width_mm - self.gauge_width_mm) / 2, self.transition_radius_mm)
        return math.sqrt(max(2 * self.transition_radius_mm * drop - drop * drop, 0.0))


class WeldConfig(StrictModel):
    """Ranges the weld cap's geometry is drawn from; values vary smoothly along the weld."""

    treatment: Literal["as-welded", "hfmi-treated", "burr-ground"] = "as-welded"
    cap_height_mm: FloatRange = (1.0, 3.0)
    cap_width_mm: FloatRange = (15.0, 20.0)
    toe_radius_mm: FloatRange = (0.3, 2.0)
    flank_angle_deg: FloatRange = (20.0, 50.0)
    ripple_amplitude_mm: FloatRange = (0.03, 0.12)
    ripple_wavelength_mm: FloatRange = (1.5, 3.0)
    undercut_depth_mm: FloatRange = (0.0, 0.5)
    undercut_probability: float = Field(default=0.3, ge=0, le=1)
    bead_wander_mm: float = Field(default=0.4, ge=0, le=5)
    axial_misalignment_mm: FloatRange = (0.0, 1.0)
    angular_misalignment_deg: FloatRange = (0.0, 0.4)
    hfmi_groove_width_mm: FloatRange = (3.0, 6.0)
    hfmi_groove_depth_mm: FloatRange = (0.2, 0.6)
    burr_width_mm: FloatRange = (5.0, 8.0)
    burr_depth_mm: FloatRange = (0.5, 1.0)
    variation_length_mm: float = Field(default=15.0, gt=0, description="correlation length along the weld")

    @model_validator(mode="after")
    def _possible(self) -> "WeldConfig":
        for name in ("cap_height_mm", "cap_width_mm", "toe_radius_mm", "ripple_wavelength_mm",
                     "hfmi_groove_width_mm", "burr_width_mm"):
            if getattr(self, name)[0] <= 0:
                raise ValueError(f"{name} must be positive")
        for name in ("ripple_amplitude_mm", "undercut_depth_mm", "axial_misalignment_mm",
                     "angular_misalignment_deg", "hfmi_groove_depth_mm", "burr_depth_mm"):
            if getattr(self, name)[0] < 0:
                raise ValueError(f"{name} must not be negative")
        if not (0 < self.flank_angle_deg[0] and self.flank_angle_deg[1] < 80):
            raise ValueError("flank_angle_deg must lie within (0, 80) degrees")
        if self.cap_height_mm[1] * 2 > self.cap_width_mm[0]:
            raise ValueError("cap_height_mm must be less than half of cap_width_mm")
        if self.hfmi_groove_depth_mm[1] * 2 >= self.hfmi_groove_width_mm[0]:
            raise ValueError("hfmi_groove_depth_mm must be less than half of hfmi_groove_width_mm")
        if self.burr_depth_mm[1] * 2 >= self.burr_width_mm[0]:
            raise ValueError("burr_depth_mm must be less than half of burr_width_mm")
        return self


class StickerConfig(StrictModel):
    diameter_mm: float = Field(default=6.0, gt=0, le=50)
    thickness_mm: float = Field(default=0.1, ge=0, le=1)
    min_common: int = Field(default=3, ge=3, description="stickers every overlapping pass pair must share")
    min_spread_mm: float = Field(default=4.0, gt=0, description="the common stickers' extent off their best line")
    spacing_factor: float = Field(default=1.6, ge=1.05, description="min centre distance in diameters")
    overlap_area_mm2: float = Field(default=300.0, gt=0, description=(
        "two passes overlap when the sticker-eligible surface both see, where a whole sticker "
        "fits, covers this area and is not a mere line"))
    weld_clearance_mm: float = Field(default=2.0, ge=0, description="gap kept between sticker and weld zone")
    edge_clearance_mm: float = Field(default=1.0, ge=0, description="gap kept between sticker and face edge")
    fill_density_per_1000mm2: float = Field(default=0.5, ge=0, description="extra random stickers on faces")
    n_fixture: int = Field(default=6, ge=0, le=100)


class FixtureConfig(StrictModel):
    """Base plate (top face at world z = 0) and two support blocks under the grips."""

    plate_size_mm: Vector3 = (800.0, 320.0, 15.0)
    block_size_mm: Vector3 = (60.0, 50.0, 40.0)
    block_centres_x_mm: tuple[float, float] = (-240.0, 240.0)

    @model_validator(mode="after")
    def _possible(self) -> "FixtureConfig":
        if min(self.plate_size_mm) <= 0 or min(self.block_size_mm) <= 0:
            raise ValueError("fixture sizes must be positive")
        return self


class ScannerConfig(StrictModel):
    model: str = "Wenglor MLWL-class (simulated)"
    points_per_profile: int = Field(default=2048, gt=1, le=4096)
    x_spacing_mm: float = Field(default=0.02, gt=0, le=5, description="point spacing along the line at the reference distance")
    reference_distance_mm: float = Field(default=200.0, gt=0)
    z_range_mm: FloatRange = (150.0, 300.0)
    z_resolution_mm: float = Field(default=0.004, gt=0)
    camera_offset_mm: Vector3 = Field(default=(0.0, 115.0, 0.0), description="30 deg triangulation at 200 mm")
    range_noise_mm: float = Field(default=0.006, ge=0, le=1, description="1-sigma along the laser ray, sprayed steel")
    intensity_noise: float = Field(default=10.0, ge=0, description="1-sigma, in 10-bit counts")
    line_width_mm: float = Field(default=0.1, ge=0, le=2, description=(
        "laser line thickness (1/e^2 full width). A point's intensity integrates the surface over "
        "this thickness and the pixel's width along the line, so points on a sticker's rim read "
        "partly bright"))
    grazing_limit_deg: float = Field(default=82.0, gt=0, lt=90)
    dropout_rate: float = Field(default=0.002, ge=0, le=1)
    reflective_dropout_rate: float = Field(default=0.35, ge=0, le=1)
    outlier_rate: float = Field(default=0.002, ge=0, le=1)
    reflective_outlier_rate: float = Field(default=0.03, ge=0, le=1)
    outlier_offset_mm: FloatRange = (0.3, 4.0)

    @model_validator(mode="after")
    def _possible(self) -> "ScannerConfig":
        near, far = self.z_range_mm
        if not (0 < near < self.reference_distance_mm < far):
            raise ValueError("z_range_mm must be (near, far) around reference_distance_mm, near > 0")
        if self.outlier_offset_mm[0] <= 0:
            raise ValueError("outlier_offset_mm must be positive")
        return self


class RobotConfig(StrictModel):
    speed_mm_s: float = Field(default=15.0, gt=0, le=1000)
    profile_spacing_mm: float = Field(default=0.1, gt=0, le=10, description="travel between profiles")
    pose_error_translation_mm: float = Field(default=0.25, ge=0, le=10, description="1-sigma per axis, per pass")
    pose_error_rotation_deg: float = Field(default=0.02, ge=0, le=5, description="1-sigma per axis, per pass")
    speed_ripple_fraction: float = Field(default=0.01, ge=0, lt=0.5)
    speed_ripple_hz: float = Field(default=2.0, gt=0)
    encoder_noise_mm: float = Field(default=0.003, ge=0, description="noise of the logged flange poses")
    log_profile_poses: bool = True
    T_flange_sensor: Pose4x4 = [
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 25.0],
        [0.0, 0.0, 1.0, 120.0],
        [0.0, 0.0, 0.0, 1.0],
    ]

    def profile_rate_hz(self) -> float:
        return self.speed_mm_s / self.profile_spacing_mm


class WidthPass(StrictModel):
    x_mm: float = Field(description="specimen x of the line's centre")
    pitch_deg: float = Field(default=0.0, ge=-60, le=60, description="tilt of the laser plane about the travel axis")


class ScanPlanConfig(StrictModel):
    """The robot program, relative to the nominal specimen placement. Along-length passes travel
    the specimen length plus ``margin_mm`` at each end; along-width passes its grip width plus
    ``margin_mm`` at each side."""

    setups: list[Literal["top", "bottom"]] = Field(default=["top", "bottom"], min_length=1)
    margin_mm: float = Field(default=30.0, ge=0, le=500)
    vertical_offsets_mm: list[float] = Field(default=[-35.0, -21.0, -7.0, 7.0, 21.0, 35.0], min_length=1)
    inclination_deg: float = Field(default=20.0, ge=0, le=45, description=(
        "forward/backward tilt of the top-down along-length passes, alternating, so the camera "
        "looks over the weld cap as in a real cell"))
    side_rolls_deg: list[float] = Field(default=[30.0, 50.0, 70.0], description="tilted passes per side")
    width_passes: list[WidthPass] = Field(
        default=[WidthPass(x_mm=-30.0), WidthPass(x_mm=30.0),
                 WidthPass(x_mm=-26.0, pitch_deg=25.0), WidthPass(x_mm=26.0, pitch_deg=-25.0)]
    )

    @model_validator(mode="after")
    def _possible(self) -> "ScanPlanConfig":
        if len(set(self.setups)) != len(self.setups):
            raise ValueError("setups must not repeat")
        for roll in self.side_rolls_deg:
            if not (0 < roll < 85):
                raise ValueError("side_rolls_deg must lie within (0, 85) degrees")
        return self


class PositionerConfig(StrictModel):
    """A positioner turns the part between its setups instead of a hand: the part stays clamped
    (its jaws drawn as the support blocks under its grips) and its second setup is its first
    turned ``angle_deg`` about the positioner's axis. ``axis_point_mm`` and ``axis_direction``
    are the axis as calibrated (the manifest's, cell frame; the point None: along the part's
    length through its mid-plane at its nominal placement); the true axis differs from it by a
    random offset (``axis_error_mm``, one sigma, across the axis), tilt (``axis_error_deg``) and
    angle (``angle_error_deg``)."""

    axis_point_mm: tuple[float, float, float] | None = None
    axis_direction: tuple[float, float, float] = (1.0, 0.0, 0.0)
    angle_deg: float = Field(default=180.0, ge=-360, le=360)
    axis_error_mm: float = Field(default=0.05, ge=0, le=10)
    axis_error_deg: float = Field(default=0.02, ge=0, le=5)
    angle_error_deg: float = Field(default=0.01, ge=0, le=5)
    tolerance_mm: float = Field(default=1.0, gt=0, le=50, description=(
        "the manifest's: how far a sticker may lie from where the calibrated turn puts it"))


class PlacementConfig(StrictModel):
    """How far the hand placement of each setup strays from the nominal one."""

    translation_mm: float = Field(default=10.0, ge=0, le=100)
    yaw_deg: float = Field(default=2.0, ge=0, le=20)


class TrueMeshConfig(StrictModel):
    """Resolution of the true surface mesh the scanner is simulated against."""

    plate_dx_mm: float = Field(default=1.0, gt=0, le=20)
    weld_dx_mm: float = Field(default=0.1, gt=0, le=5)
    toe_dx_mm: float = Field(default=0.03, gt=0, le=5)
    across_nodes: int = Field(default=1000, ge=8, le=20000, description="nodes across the width")
    wall_rows: int = Field(default=21, ge=2, le=1000)


class TJointConfig(StrictModel):
    """A T-joint (``simulator.tjoint``): a stem plate welded upright across a base plate by two
    convex fillet welds, one on each side of the stem. Specimen frame as the manifest's
    ``TJointSpecimen``: origin at the base plate's centre (mid-thickness), x across the stem, y along
    it and its welds, z toward the stem. The weld's toe radius, ripples, bead wander and variation
    length come from ``weld``; the scan plan's setups and margin from ``plan``. With ``stems:
    both`` a cruciform joint (the manifest's ``CruciformSpecimen``): a second stem of the same
    size on the base plate's other face, in the same plane, with its own two fillets, four in all.
    A T-joint's config is written without ``stems`` (``simulation_json``), as before cruciforms."""

    stems: Literal["one", "both"] = Field(default="one", description=(
        "one: a T-joint; both: a cruciform joint (a stem on each face of the base plate)"))
    base_length_mm: float = Field(default=260.0, gt=0, le=1000)
    base_width_mm: float = Field(default=120.0, gt=0, le=1000)
    base_thickness_mm: float = Field(default=12.0, gt=0, le=100)
    stem_height_mm: float = Field(default=60.0, gt=0, le=500)
    stem_thickness_mm: float = Field(default=10.0, gt=0, le=100)
    leg_mm: FloatRange = Field(default=(6.0, 8.0), description="fillet legs, along the base and up the stem")
    convexity_mm: FloatRange = Field(default=(0.4, 1.2), description="the fillet face's rise above its legs' chord")
    shape_exponent: float = Field(default=2.5, ge=1.2, le=10, description="of the convex face, as the butt cap's")
    along_weld_dx_mm: float = Field(default=0.25, gt=0, le=5, description="mesh stations along the weld (y)")
    wall_stickers: bool = Field(default=True, description=(
        "stickers on the base plate's walls (its four 12 mm sides): the only surfaces both setups see"))
    wall_sticker_pitch_mm: float = Field(default=20.0, gt=0, description="along each wall")
    fillet_rolls_deg: tuple[float, float] = Field(default=(40.0, 65.0), description=(
        "the two passes along each weld, rolled toward it from the vertical: both toes seen"))
    base_roll_deg: float = Field(default=35.0, ge=0, lt=85, description="outer passes, rolled out to see the ends")
    wall_roll_deg: float = Field(default=50.0, gt=0, lt=85, description="passes along the base's long walls")

    @model_validator(mode="after")
    def _possible(self) -> "TJointConfig":
        if self.leg_mm[0] <= 0 or self.convexity_mm[0] < 0:
            raise ValueError("leg_mm must be positive and convexity_mm not negative")
        if self.convexity_mm[1] * 4 > self.leg_mm[0]:
            raise ValueError("convexity_mm must stay under a quarter of leg_mm")
        if self.leg_mm[1] * 2 >= self.stem_height_mm or self.stem_thickness_mm / 2 + self.leg_mm[1] + 20 > \
                self.base_length_mm / 2:
            raise ValueError("the fillet legs do not fit on the stem and the base plate")
        return self


class SimulationConfig(StrictModel):
    preset: str = "custom"
    seed: int = Field(default=0, ge=0)
    sample_id: str = Field(default="sim-0000", pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
    specimen: SpecimenConfig = SpecimenConfig()
    weld: WeldConfig = WeldConfig()
    stickers: StickerConfig = StickerConfig()
    fixture: FixtureConfig = FixtureConfig()
    scanner: ScannerConfig = ScannerConfig()
    robot: RobotConfig = RobotConfig()
    plan: ScanPlanConfig = ScanPlanConfig()
    placement: PlacementConfig = PlacementConfig()
    mesh: TrueMeshConfig = TrueMeshConfig()
    tjoint: TJointConfig | None = Field(default=None, description=(
        "simulate a T-joint or a cruciform joint (simulator.tjoint) instead of the dog-bone of ``specimen``"))
    chunk_profiles: int = Field(default=256, ge=1, le=100000, description="profiles per zarr chunk and per render batch")
    positioner: PositionerConfig | None = Field(default=None, description=(
        "the part turned between its setups by a positioner instead of by hand"))

    @model_validator(mode="after")
    def _possible(self) -> "SimulationConfig":
        spec, weld = self.specimen, self.weld
        half_weld = weld.cap_width_mm[1] / 2 + max(weld.hfmi_groove_width_mm[1], weld.burr_width_mm[1])
        if 2 * half_weld + 2 * self.stickers.diameter_mm > spec.gauge_length_mm + 2 * spec.transition_length_mm():
            raise ValueError("weld.cap_width_mm is too wide for the specimen's gauge section")
        if weld.cap_height_mm[1] >= spec.thickness_mm:
            raise ValueError("weld.cap_height_mm must be smaller than specimen.thickness_mm")
        blocks = self.fixture.block_centres_x_mm
        if self.tjoint is not None:
            tj = self.tjoint
            if max(abs(b) for b in blocks) + self.fixture.block_size_mm[0] / 2 > tj.base_length_mm / 2 or \
                    min(abs(b) for b in blocks) - self.fixture.block_size_mm[0] / 2 < \
                    tj.stem_thickness_mm / 2 + tj.leg_mm[1] + 2:
                raise ValueError("fixture.block_centres_x_mm must put the support blocks under the base plate, "
                                 "clear of the stem and its welds")
            if self.fixture.block_size_mm[2] < tj.stem_height_mm + 10:
                raise ValueError("fixture.block_size_mm: the blocks must be taller than the stem (turned over, "
                                 "it hangs between them)")
            return self
        if max(abs(b) for b in blocks) + self.fixture.block_size_mm[0] / 2 > spec.length_mm / 2:
            raise ValueError("fixture.block_centres_x_mm put a support block beyond the specimen's ends")
        if self.fixture.block_size_mm[1] >= spec.grip_width_mm:
            raise ValueError("fixture.block_size_mm must be narrower (y) than specimen.grip_width_mm")
        return self

    def simulation_json(self) -> str:
        """The config as ``truth/simulation.json`` holds it: a dog-bone's without ``tjoint`` (as
        before T-joints existed), a T-joint's without ``tjoint.stems`` (as before cruciforms),
        without ``positioner`` when the part is turned by hand."""
        exclude: dict = {"tjoint": True} if self.tjoint is None else \
            {"tjoint": {"stems"}} if self.tjoint.stems == "one" else {}
        if self.positioner is None:  # as before positioners
            exclude["positioner"] = True
        return self.model_dump_json(indent=2, exclude=exclude or None) + "\n"
