"""The sample manifest: what a scanning cell (or the simulator) writes next to its pass files.

A sample is one welded part (the specimen) scanned in one or more setups (e.g. top, then bottom
after the part was turned by hand). Each setup holds passes; a pass is one linear robot sweep of
the line scanner, stored as a chunked zarr group (format in ``data_catalog.passes``).

The specimen is one of a few kinds of part (``specimen.kind``: a dog-bone, a butt-welded plate, a
T-joint, a cruciform joint, or any part given by its drawing mesh), each with its own specimen
frame; the weld is given by its weld lines, polylines in that frame (``weld.weld_lines``).
Schema 1.0 (read, never written) knew the dog-bone alone and gave its weld by one number,
``weld.centre_x_mm``: ``SampleManifest.weld_lines`` turns it into the same lines.
"""

from __future__ import annotations

import math
from abc import abstractmethod
from pathlib import PurePosixPath
from typing import Any, ClassVar, Literal, Union

from pydantic import (AfterValidator, Field, SerializerFunctionWrapHandler, ValidationInfo, ValidatorFunctionWrapHandler,
                      WrapValidator, field_validator, model_serializer, model_validator)
from typing_extensions import Annotated

from schemas.common import AwareDatetime, Pose4x4, StrictModel, Vector3, without_none

__all__ = [
    "MANIFEST_SCHEMA_VERSION",
    "WELD_LINE_MARGIN_MM",
    "JOINTS",
    "DogBoneSpecimen",
    "LoadCase",
    "PlateSpecimen",
    "TJointSpecimen",
    "CruciformSpecimen",
    "DrawingSpecimen",
    "UNITS_TO_MM",
    "SPECIMEN_KINDS",
    "SpecimenGeometry",
    "WeldLine",
    "WeldDescription",
    "CentreLineWeld",
    "dog_bone_weld_lines",
    "ScannerSettings",
    "NominalMotion",
    "PassEntry",
    "ScanEntry",
    "REGISTRATIONS",
    "Setup",
    "SampleManifest",
]

MANIFEST_SCHEMA_VERSION = "1.1"  # what is written; 1.0 is read too (SampleManifest.schema_version)
WELD_LINE_MARGIN_MM = 10.0  # how far a weld line may stand outside the part's box (a weld cap, a fillet)

Treatment = Literal["as-welded", "hfmi-treated", "burr-ground"]
Joint = Literal["double-sided butt", "single-V butt", "double-V butt", "fillet", "double fillet",
                "cruciform fillet", "other"]
JOINTS: tuple[str, ...] = Joint.__args__
_BUTT_JOINTS = ("double-sided butt", "single-V butt", "double-V butt", "other")
_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"

Bounds = tuple[tuple[float, float, float], tuple[float, float, float]]


def _relative_file(what: str):
    def check(value: str) -> str:
        path = PurePosixPath(value)
        if "\\" in value or path.is_absolute() or value.startswith("~"):
            raise ValueError(f"{what} {value!r} must be a relative POSIX path inside the sample folder")
        if any(part == ".." for part in path.parts) or not path.parts:
            raise ValueError(f"{what} {value!r} must not leave the sample folder ('..' is not allowed)")
        return value
    return check


RelativeFile = Annotated[str, AfterValidator(_relative_file("pass file"))]


def _check_millimetres(dimensions: dict[str, float]) -> None:
    """Refuse a part whose main ``dimensions`` (name -> mm) are under 1 mm: given in metres."""
    small = {k: v for k, v in dimensions.items() if v < 1.0}
    if small:
        raise ValueError(f"{', '.join(f'{k} {v:g}' for k, v in small.items())}: under 1 mm, not a part a "
                         "scanning cell measures; were the dimensions given in metres? expected millimetres")


class _Part(StrictModel):
    """What every kind of specimen says: the joints it can carry, its bounding box."""

    joints: ClassVar[tuple[str, ...]]  # the values of ``weld.joint`` that fit the kind

    @abstractmethod
    def bounds_mm(self) -> Bounds:
        """The part's axis-aligned bounding box in its specimen frame, mm: (min corner, max corner)."""


class DogBoneSpecimen(_Part):
    """Nominal (drawing) geometry of a dog-bone specimen; the specimen frame has its origin at
    the centre, x along the length, y across the width, z through the thickness."""

    joints: ClassVar[tuple[str, ...]] = _BUTT_JOINTS
    kind: Literal["dog-bone"] = "dog-bone"
    length_mm: float = Field(gt=0, le=5000)
    grip_width_mm: float = Field(gt=0, le=2000)
    gauge_width_mm: float = Field(gt=0, le=2000)
    gauge_length_mm: float = Field(ge=0, le=5000)
    transition_radius_mm: float = Field(gt=0, le=5000)
    thickness_mm: float = Field(gt=0, le=500)

    @model_validator(mode="after")
    def _in_millimetres(self) -> "DogBoneSpecimen":
        _check_millimetres({"length_mm": self.length_mm, "grip_width_mm": self.grip_width_mm,
                            "thickness_mm": self.thickness_mm})
        return self

    def bounds_mm(self) -> Bounds:
        x, y, z = self.length_mm / 2, self.grip_width_mm / 2, self.thickness_mm / 2
        return (-x, -y, -z), (x, y, z)


class PlateSpecimen(_Part):
    """Two plates butt-welded edge to edge into one rectangular plate (the joint's groove, single
    or double V, in ``weld.joint``). The specimen frame has its origin at the plate's centre, x
    along ``length_mm`` (across the weld), y along ``width_mm`` (along the weld), z through the
    thickness; the face at z = +thickness/2 is the top."""

    joints: ClassVar[tuple[str, ...]] = _BUTT_JOINTS
    kind: Literal["plate"]
    length_mm: float = Field(gt=0, le=5000)
    width_mm: float = Field(gt=0, le=5000)
    thickness_mm: float = Field(gt=0, le=500)

    @model_validator(mode="after")
    def _in_millimetres(self) -> "PlateSpecimen":
        _check_millimetres({"length_mm": self.length_mm, "width_mm": self.width_mm,
                            "thickness_mm": self.thickness_mm})
        return self

    def bounds_mm(self) -> Bounds:
        x, y, z = self.length_mm / 2, self.width_mm / 2, self.thickness_mm / 2
        return (-x, -y, -z), (x, y, z)


class _StemmedPart(_Part):
    """A base plate with a stem plate welded upright across its whole width (T-joint, cruciform)."""

    base_length_mm: float = Field(gt=0, le=5000)
    base_width_mm: float = Field(gt=0, le=5000)
    base_thickness_mm: float = Field(gt=0, le=500)
    stem_height_mm: float = Field(gt=0, le=5000, description="from the base plate's face to the stem's end")
    stem_thickness_mm: float = Field(gt=0, le=500)
    stem_x_mm: float = Field(default=0.0, description="x of the stem's mid-plane, specimen frame")

    @model_validator(mode="after")
    def _plausible(self) -> "_StemmedPart":
        _check_millimetres({"base_length_mm": self.base_length_mm, "base_width_mm": self.base_width_mm,
                            "base_thickness_mm": self.base_thickness_mm})
        if abs(self.stem_x_mm) + self.stem_thickness_mm / 2 > self.base_length_mm / 2:
            raise ValueError(f"the stem (stem_x_mm {self.stem_x_mm:g}, stem_thickness_mm {self.stem_thickness_mm:g}) "
                             f"overhangs the base plate (base_length_mm {self.base_length_mm:g}); expected "
                             "|stem_x_mm| + stem_thickness_mm/2 <= base_length_mm/2")
        return self


class TJointSpecimen(_StemmedPart):
    """A T-joint: a stem plate welded upright on one face of a base plate, across its whole width.
    The specimen frame has its origin at the centre of the base plate (mid-thickness), x along the
    base plate's length (across the stem), y along its width (along the stem and its welds), z
    through its thickness toward the stem. The stem's mid-plane is x = ``stem_x_mm``; it stands
    from the base plate's face (z = base_thickness/2) to z = base_thickness/2 + stem_height_mm."""

    joints: ClassVar[tuple[str, ...]] = ("fillet", "double fillet", "other")
    kind: Literal["t-joint"]

    def bounds_mm(self) -> Bounds:
        x, y, z = self.base_length_mm / 2, self.base_width_mm / 2, self.base_thickness_mm / 2
        return (-x, -y, -z), (x, y, z + self.stem_height_mm)


class CruciformSpecimen(_StemmedPart):
    """A cruciform joint: stem plates welded upright on both faces of a base plate, in one plane,
    across its whole width. The specimen frame is the T-joint's: origin at the centre of the base
    plate (mid-thickness), x along the base plate's length (across the stems), y along its width
    (along the stems and their welds), z through its thickness. The stems' mid-plane is
    x = ``stem_x_mm``; each stands ``stem_height_mm`` from its face (z = +-base_thickness/2)."""

    joints: ClassVar[tuple[str, ...]] = ("cruciform fillet", "other")
    kind: Literal["cruciform"]

    def bounds_mm(self) -> Bounds:
        x, y, z = self.base_length_mm / 2, self.base_width_mm / 2, self.base_thickness_mm / 2
        return (-x, -y, -z - self.stem_height_mm), (x, y, z + self.stem_height_mm)


UNITS_TO_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}
"""Millimetres per unit: a drawing's ``units``, an imported point cloud's (data_catalog.pointclouds)."""


def _check_drawing_suffix(value: str) -> str:
    if PurePosixPath(value).suffix.lower() not in (".stl", ".ply"):
        raise ValueError(f"drawing file {value!r}: expected a mesh file, .stl or .ply")
    return value


class DrawingSpecimen(_Part):
    """Any other part, given by its drawing: a triangle mesh (STL or PLY) inside the sample folder.
    The specimen frame is the drawing's own coordinate frame, its coordinates in ``units`` scaled
    to millimetres. ``bounds_mm``: the drawing's axis-aligned bounding box in that frame, mm (min
    corner, max corner), for plausibility checks without reading the mesh; ``sha256``: the file's
    content hash (checked, with the file, before a reconstruction)."""

    joints: ClassVar[tuple[str, ...]] = JOINTS
    kind: Literal["drawing"]
    file: Annotated[str, AfterValidator(_relative_file("drawing file")), AfterValidator(_check_drawing_suffix)]
    units: Literal["mm", "cm", "m", "in"]
    sha256: str = Field(pattern=r"^[0-9a-f]{64}$")
    bounds: tuple[Vector3, Vector3] = Field(description="min corner, max corner; specimen frame, mm")

    @model_validator(mode="after")
    def _a_box(self) -> "DrawingSpecimen":
        lo, hi = self.bounds
        if any(b <= a for a, b in zip(lo, hi)):
            raise ValueError(f"bounds {list(lo)} .. {list(hi)}: expected the min corner below the max corner "
                             "on every axis")
        _check_millimetres({"bounds (largest extent)": max(b - a for a, b in zip(lo, hi))})
        return self

    def bounds_mm(self) -> Bounds:
        return self.bounds


SPECIMEN_KINDS: dict[str, type[_Part]] = {"dog-bone": DogBoneSpecimen, "plate": PlateSpecimen,
                                          "t-joint": TJointSpecimen, "cruciform": CruciformSpecimen,
                                          "drawing": DrawingSpecimen}


def _specimen_of_its_kind(value: Any, handler: ValidatorFunctionWrapHandler) -> _Part:
    """Validate ``value`` as the kind it names (``kind``, default dog-bone as in schema 1.0), so
    that an error names the kind's own fields (``specimen.length_mm``) and an unknown kind the
    known ones."""
    if isinstance(value, tuple(SPECIMEN_KINDS.values())):
        return value
    if not isinstance(value, dict):
        return handler(value)
    kind = value.get("kind", "dog-bone")
    if not isinstance(kind, str) or kind not in SPECIMEN_KINDS:
        raise ValueError(f"kind {kind!r} is not a specimen kind weldrecon knows; expected one of "
                         f"{', '.join(SPECIMEN_KINDS)}")
    return SPECIMEN_KINDS[kind].model_validate(value)


SpecimenGeometry = Annotated[
    Union[DogBoneSpecimen, PlateSpecimen, TJointSpecimen, CruciformSpecimen, DrawingSpecimen],
    Field(discriminator="kind"), WrapValidator(_specimen_of_its_kind)]
"""The specimen, any kind (``specimen.kind``: dog-bone, plate, t-joint, cruciform, drawing)."""


class WeldLine(StrictModel):
    """One line of the weld: a polyline in the specimen frame, mm (a weld's centre line on one
    face, a toe, a fillet's root); the reconstruction keeps its full resolution around it."""

    name: str = Field(pattern=_ID_PATTERN)
    points_mm: list[Vector3] = Field(min_length=2, max_length=1000, description="(k, 3), specimen frame, mm")
    label: str | None = Field(default=None, min_length=1, max_length=64,
                              description="where the line lies, e.g. 'top toe A'")

    @field_validator("points_mm")
    @classmethod
    def _no_repeated_point(cls, value: list[Vector3]) -> list[Vector3]:
        for k in range(1, len(value)):
            if value[k] == value[k - 1]:
                raise ValueError(f"points {k - 1} and {k} are the same point {list(value[k])}; expected each "
                                 "point of the polyline once")
        return value


def dog_bone_weld_lines(specimen: DogBoneSpecimen, centre_x_mm: float) -> list[WeldLine]:
    """The weld lines of a dog-bone's double-sided butt weld across it at x = ``centre_x_mm``
    (specimen frame, mm): on the top face (z = +thickness/2) and on the bottom face
    (z = -thickness/2), each across the full grip width. What a schema 1.0 manifest's
    ``weld.centre_x_mm`` means; the simulator writes these lines."""
    y, z = specimen.grip_width_mm / 2, specimen.thickness_mm / 2
    return [WeldLine(name=side, label=f"{side} face, weld centre line",
                     points_mm=[(centre_x_mm, -y, sign * z), (centre_x_mm, y, sign * z)])
            for side, sign in (("top", 1.0), ("bottom", -1.0))]


class WeldDescription(StrictModel):
    """The weld (schema 1.1): how it was made and treated, its joint, and where it runs:
    ``weld_lines``, named polylines in the specimen frame, mm (at least one)."""

    process: str = "GMAW"
    joint: Joint
    weld_lines: list[WeldLine] = Field(min_length=1)
    treatment: Treatment = "as-welded"

    @field_validator("weld_lines")
    @classmethod
    def _unique_names(cls, value: list[WeldLine]) -> list[WeldLine]:
        names = [line.name for line in value]
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise ValueError(f"weld line names must be unique, repeated: {twice}")
        return value


class CentreLineWeld(StrictModel):
    """The weld of a schema 1.0 manifest: a dog-bone's double-sided butt weld across it, its
    centre line x = ``centre_x_mm`` of the specimen frame. Read, never written:
    ``SampleManifest.weld_lines`` gives its lines (``dog_bone_weld_lines``)."""

    process: str = "GMAW"
    joint: Literal["double-sided butt"] = "double-sided butt"
    centre_x_mm: float = Field(default=0.0, description="weld centre line, specimen frame")
    treatment: Treatment = "as-welded"


class ScannerSettings(StrictModel):
    """The line scanner and how it was set. The sensor frame S: origin at the laser emitter,
    z along the central laser ray (away from the sensor), x along the projected line; the laser
    plane is S's x-z plane. A point is stored as (X, Z) in S."""

    model: str
    points_per_profile: int = Field(gt=0, le=4096)
    x_spacing_mm: float = Field(gt=0, le=10, description="spacing along the line at the reference distance")
    z_resolution_mm: float = Field(gt=0, le=1)
    reference_distance_mm: float = Field(gt=0)
    z_range_mm: tuple[float, float]
    intensity_bits: Literal[10] = 10
    camera_offset_mm: Vector3 = Field(description="camera centre in the sensor frame S")
    T_flange_sensor: Pose4x4

    @field_validator("z_range_mm")
    @classmethod
    def _z_range_ordered(cls, value: tuple[float, float]) -> tuple[float, float]:
        if not (0 < value[0] < value[1]):
            raise ValueError("z_range_mm must be (near, far) with 0 < near < far")
        return value


class NominalMotion(StrictModel):
    """The commanded linear sweep of one pass: flange pose at the first profile, then straight
    along ``direction_world`` at ``speed_mm_s``, one profile every 1/``profile_rate_hz`` s."""

    T_world_flange_start: Pose4x4
    direction_world: Vector3
    speed_mm_s: float = Field(gt=0, le=1000)
    profile_rate_hz: float = Field(gt=0, le=100000)
    length_mm: float = Field(gt=0, le=10000)

    @field_validator("direction_world")
    @classmethod
    def _unit_direction(cls, value: Vector3) -> Vector3:
        if abs(math.sqrt(sum(v * v for v in value)) - 1.0) > 1e-6:
            raise ValueError("direction_world must be a unit vector")
        return value


class PassEntry(StrictModel):
    """One pass. ``direction``: a label for people ("along-length", "across-weld", "rolled 45");
    the reconstruction goes by ``nominal_motion.direction_world`` alone."""

    pass_id: str = Field(pattern=_ID_PATTERN)
    file: RelativeFile
    direction: str = Field(min_length=1, max_length=64, pattern=r"\S")
    n_profiles: int = Field(gt=0, le=10_000_000)
    duration_s: float = Field(gt=0)
    nominal_motion: NominalMotion
    has_profile_poses: bool = Field(description="the pass file holds the robot's flange pose per profile")
    content_sha256: str | None = Field(default=None, pattern=r"^[0-9a-f]{64}$")


class ScanEntry(StrictModel):
    """One scan of a sample registered on its surfaces (``registration: surfaces``): a point cloud
    from any scanner, imported by ``weldrecon import-scans`` into a scan store
    (``data_catalog.scans``: its points in the scan's own frame, and its pose ``T_world_pass``
    when one was given). ``view_direction``: from the surface toward the sensor, in the scan's
    frame (normals are turned toward it); ``source``: the file it was imported from (a label)."""

    kind: Literal["scan"]
    pass_id: str = Field(pattern=_ID_PATTERN)
    file: RelativeFile
    n_points: int = Field(gt=0, le=1_000_000_000)
    has_pose: bool = Field(description="the scan store holds the scan's pose T_world_pass (a .conf, E57)")
    view_direction: Vector3 = Field(description="from the surface toward the sensor, scan frame (unit)")
    source: str = Field(default="", max_length=1000)
    content_sha256: str | None = Field(default=None, pattern=r"^[0-9a-f]{64}$")

    @field_validator("view_direction")
    @classmethod
    def _unit_view(cls, value: Vector3) -> Vector3:
        norm = math.sqrt(sum(v * v for v in value))
        if abs(norm - 1.0) > 1e-6:
            raise ValueError(f"view_direction must be a unit vector, got norm {norm:g}")
        return value


def _pass_of_its_kind(value: Any, handler: ValidatorFunctionWrapHandler) -> "PassEntry | ScanEntry":
    """A scan entry (``kind: scan``) or a robot pass (no ``kind``), so that an error names the
    entry's own fields."""
    if isinstance(value, (PassEntry, ScanEntry)):
        return value
    if not isinstance(value, dict):
        return handler(value)
    kind = value.get("kind")
    if kind is None:
        return PassEntry.model_validate(value)
    if kind != "scan":
        raise ValueError(f"kind {kind!r} is not a pass kind weldrecon knows; expected 'scan' (a point cloud) or no "
                         "kind (a robot pass of the line scanner)")
    return ScanEntry.model_validate(value)


AnyPass = Annotated[Union[PassEntry, ScanEntry], WrapValidator(_pass_of_its_kind)]
"""A setup's pass: a robot pass of the line scanner (``PassEntry``) or an imported scan (``ScanEntry``)."""

REGISTRATIONS = ("targets", "surfaces")


class PositionerTurn(StrictModel):
    """This setup is an earlier one's turned by the cell's positioner instead of by hand: the part,
    still clamped, turned ``angle_deg`` (right-handed) about the positioner's axis, the line
    through ``axis_point_mm`` along ``axis_direction`` in the cell's frame, as calibrated. The
    registration takes the turn as its prior for matching this setup to ``from_setup`` and checks
    it against the stickers both see: a sticker must lie within ``tolerance_mm`` (the calibration's
    error at the part) and the robot's coarse error (``registration.max_offset_mm``) of where the
    turn puts it; the axis the stickers give is reported beside the calibrated one."""

    from_setup: str = Field(pattern=_ID_PATTERN)
    axis_point_mm: Vector3
    axis_direction: Vector3
    angle_deg: float = Field(ge=-360, le=360)
    tolerance_mm: float = Field(default=1.0, gt=0, le=50)

    @model_validator(mode="after")
    def _direction(self) -> "PositionerTurn":
        if not math.isfinite(sum(self.axis_direction)) or math.hypot(*self.axis_direction) < 1e-9:
            raise ValueError("axis_direction must be a nonzero vector")
        return self


class Setup(StrictModel):
    """One placement of the specimen in the cell; the robot frame ('world') is the cell's.

    ``T_world_specimen_nominal``: where the fixture puts the specimen frame in this setup, as
    drawn (optional); the specimen lies within ``placement_tolerance_mm`` of it at its weld lines.
    With it, the reconstruction knows roughly where the weld is before it has seen the weld and
    keeps that zone at full resolution."""

    name: str = Field(pattern=_ID_PATTERN)
    description: str = ""
    passes: list[AnyPass] = Field(min_length=1)
    T_world_specimen_nominal: Pose4x4 | None = None
    placement_tolerance_mm: float = Field(default=0.0, ge=0, le=1000, description=(
        "how far the specimen's weld lines may lie from where T_world_specimen_nominal puts them"))
    positioner: PositionerTurn | None = Field(default=None, description=(
        "this setup is an earlier one's turned by the cell's positioner (not by hand)"))

    @model_serializer(mode="wrap")
    def _turned_by_hand_unsaid(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        """Written as before positioners for a setup turned by hand."""
        return without_none(handler(self), "positioner")


class LoadCase(StrictModel):
    """The load the part is tested or designed for (schema 1.1, optional). ``axial`` (the default):
    tension across the weld, the part pulled along its length by its ends (a butt weld's fatigue
    test; for a T-joint or a cruciform, its base plate pulled along its length, across the stems:
    the non-load-carrying fillet weld's test); the nominal stress is the force over the plate's
    section at the toe. ``bending``: the part bent about the axis along the weld, the weld zone in
    pure bending as between the inner rollers of a 4-point (or under a 3-point) bending fatigue
    test, the top face (the first measured weld line's face, the sections' +y) stretched; the nominal
    stress is the bending moment per unit width over the section modulus at the toe, 6 M / t^2 with
    t the toe's plate thickness, with the top face's sign. ``nominal_stress_range_mpa``: the range
    of that nominal stress in each load cycle, for the fatigue estimate (``stress.notch_stress``);
    ``stress_ratio`` the cycle's smallest over its largest stress, recorded with it (the IIW notch
    stress classes hold for any ratio as welded)."""

    kind: Literal["axial", "bending"] = "axial"
    nominal_stress_range_mpa: float | None = Field(default=None, gt=0, le=2000, description=(
        "nominal stress range of a load cycle, MPa (axial: force over the plate's section; bending: 6 M / t^2 at "
        "the top face)"))
    stress_ratio: float | None = Field(default=None, ge=-1, lt=1, description="smallest over largest stress of a cycle")


class SampleManifest(StrictModel):
    """A sample's manifest. ``schema_version`` 1.1 is written; 1.0 (a dog-bone, its weld given by
    ``centre_x_mm``: ``CentreLineWeld``) is read as it is. Read the weld's lines through
    ``weld_lines()``, whatever the version."""

    schema_version: Literal["1.0", "1.1"]  # required: a file of another version is told apart, never guessed
    units: Literal["mm"]
    sample_id: str = Field(pattern=_ID_PATTERN)
    created: AwareDatetime
    material: str = "S355"
    registration: Literal["targets", "surfaces"] = Field(default="targets", description=(
        "targets: the passes are registered on their sticker targets (the paper's method; specimen, "
        "weld, sticker_diameter_mm and scanner required); surfaces: imported scans (kind scan) "
        "registered on their overlapping surfaces, from their given poses or from none"))
    specimen: SpecimenGeometry | None = None
    weld: Union[WeldDescription, CentreLineWeld] | None = Field(default=None, description=(
        "schema_version 1.1: WeldDescription (weld_lines); 1.0: CentreLineWeld (centre_x_mm)"))
    sticker_diameter_mm: float | None = Field(default=None, gt=0, le=100)
    scanner: ScannerSettings | None = None
    load: LoadCase | None = Field(default=None, description=(
        "the load the part is tested or designed for (axial or bending); none: axial tension across the weld, no "
        "fatigue estimate"))
    setups: list[Setup] = Field(min_length=1)

    @field_validator("weld", mode="wrap")
    @classmethod
    def _weld_of_its_version(cls, value: Any, handler: ValidatorFunctionWrapHandler,
                             info: ValidationInfo) -> WeldDescription | CentreLineWeld:
        """The weld in the form of the manifest's schema_version, so that an error names that
        form's fields. When schema_version itself was refused, its error stands alone (the
        manifest is refused whatever the weld)."""
        version = info.data.get("schema_version")
        if version is None or value is None:
            return value
        return (CentreLineWeld if version == "1.0" else WeldDescription).model_validate(value)

    @model_validator(mode="after")
    def _unique_names(self) -> "SampleManifest":
        setups = [s.name for s in self.setups]
        if len(set(setups)) != len(setups):
            raise ValueError(f"setup names must be unique, got {setups}")
        for k, s in enumerate(self.setups):
            if s.positioner is not None and s.positioner.from_setup not in setups[:k]:
                raise ValueError(f"setups.{k}.positioner.from_setup: {s.positioner.from_setup!r} is not a setup "
                                 f"before {s.name!r} (expected one of {setups[:k]})")
        ids = [p.pass_id for s in self.setups for p in s.passes]
        dupes = sorted({i for i in ids if ids.count(i) > 1})
        if dupes:
            raise ValueError(f"pass ids must be unique across setups, repeated: {dupes}")
        files = [(p.file, p.pass_id) for s in self.setups for p in s.passes]
        shared = {f: [i for g, i in files if g == f] for f, _ in files}
        shared = {f: ids for f, ids in shared.items() if len(ids) > 1}
        if shared:
            raise ValueError("each pass needs a file of its own; " + "; ".join(
                f"passes {', '.join(ids)} all refer to {f}" for f, ids in sorted(shared.items())))
        return self

    @model_validator(mode="after")
    def _sections_of_its_registration(self) -> "SampleManifest":
        """A sticker sample needs its part, weld, stickers and scanner, and robot passes; a
        surfaces sample holds imported scans, all with a pose or none with one."""
        if self.registration == "targets":
            missing = [k for k in ("specimen", "weld", "sticker_diameter_mm", "scanner") if getattr(self, k) is None]
            if missing:
                raise ValueError(f"{', '.join(missing)} required: registration 'targets' (the default) registers the "
                                 "passes on their stickers; a sample of imported scans says registration 'surfaces'")
            scans = [e.pass_id for _, e in self.passes() if isinstance(e, ScanEntry)]
            if scans:
                raise ValueError(f"passes {', '.join(scans)} are scans (kind scan): they take registration 'surfaces', "
                                 "not 'targets'")
        else:
            passes = [e.pass_id for _, e in self.passes() if not isinstance(e, ScanEntry)]
            if passes:
                raise ValueError(f"passes {', '.join(passes)} are robot passes: registration 'surfaces' takes imported "
                                 "scans (kind scan); robot passes are registered on their targets")
            posed = {e.has_pose for _, e in self.passes()}
            if len(posed) > 1:
                raise ValueError("some scans have a pose and some none (has_pose); expected all or none: give every "
                                 "scan's pose, or none and let the registration find them")
            if self.specimen is not None and self.weld is None:
                raise ValueError("a specimen without its weld: give the weld too, or neither (a weld alone is "
                                 "measured in the scans' frame, where the setup's T_world_specimen_nominal puts it)")
        return self

    @model_serializer(mode="wrap")
    def _targets_unsaid(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        """Written as before for a sticker sample (no ``registration`` field, as every manifest
        written before it); the optional sections a surfaces sample leaves out are left out, and
        so is a load none was given for."""
        data = handler(self)
        if data.get("load", 0) is None:
            data.pop("load")
        if self.registration == "targets":
            data.pop("registration", None)
        else:
            for key in ("specimen", "weld", "sticker_diameter_mm", "scanner"):
                if data.get(key) is None:
                    data.pop(key, None)
        return data

    @model_validator(mode="after")
    def _weld_fits_the_part(self) -> "SampleManifest":
        if self.specimen is None or self.weld is None:
            return self
        kind = self.specimen.kind
        if self.schema_version == "1.0" and kind != "dog-bone":
            raise ValueError(f"specimen.kind {kind!r}: schema_version 1.0 describes dog-bones only; expected "
                             "schema_version 1.1 (with weld.weld_lines)")
        if self.weld.joint not in self.specimen.joints:
            raise ValueError(f"weld.joint {self.weld.joint!r} does not fit specimen.kind {kind!r}; expected one of "
                             f"{', '.join(self.specimen.joints)}")
        lo, hi = self.specimen.bounds_mm()
        for n, line in enumerate(self.weld_lines()):
            for k, point in enumerate(line.points_mm):
                outside = max(max(a - p, p - b) for p, a, b in zip(point, lo, hi))
                if outside > WELD_LINE_MARGIN_MM:
                    raise ValueError(
                        f"weld.weld_lines.{n} ({line.name}): point {k} {list(point)} lies {outside:.1f} mm outside "
                        f"the {kind}'s bounding box {list(lo)} .. {list(hi)} mm; expected weld lines in the "
                        f"specimen frame, in mm, within {WELD_LINE_MARGIN_MM:g} mm of the part")
        return self

    def weld_lines(self) -> list[WeldLine]:
        """The weld's lines in the specimen frame, mm: a 1.1 manifest's own, a 1.0 manifest's from
        its centre line (``dog_bone_weld_lines``): the one place ``centre_x_mm`` is read. None
        where the manifest gives no weld (a surfaces sample may not)."""
        if self.weld is None:
            return []
        if isinstance(self.weld, CentreLineWeld):
            return dog_bone_weld_lines(self.specimen, self.weld.centre_x_mm)
        return list(self.weld.weld_lines)

    @property
    def surfaces(self) -> bool:
        """Whether the passes are registered on their surfaces (imported scans, no stickers)."""
        return self.registration == "surfaces"

    def passes(self) -> list[tuple[str, PassEntry | ScanEntry]]:
        """All passes as ``(setup_name, entry)`` in manifest order."""
        return [(s.name, p) for s in self.setups for p in s.passes]

    def grid_pitch_mm(self, entry: PassEntry) -> tuple[float, float]:
        """The nominal spacing of a pass's organized grid, mm: between profiles (the sweep's speed
        over the profile rate) and between columns (the scanner's spacing at its reference distance)."""
        motion = entry.nominal_motion
        return motion.speed_mm_s / motion.profile_rate_hz, self.scanner.x_spacing_mm
