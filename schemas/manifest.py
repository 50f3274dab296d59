"""The sample manifest: what a scanning cell (or the simulator) writes next to its pass files.

A sample is one welded specimen scanned in one or more setups (top, then bottom after the
specimen was turned by hand). Each setup holds passes; a pass is one linear robot sweep of the
line scanner, stored as a chunked zarr group (format in ``data_catalog.passes``).
"""

from __future__ import annotations

import math
from datetime import datetime
from pathlib import PurePosixPath
from typing import Literal

from pydantic import AfterValidator, Field, field_validator, model_validator
from typing_extensions import Annotated

from schemas.common import Pose4x4, StrictModel, Vector3

__all__ = [
    "MANIFEST_SCHEMA_VERSION",
    "SpecimenGeometry",
    "WeldDescription",
    "ScannerSettings",
    "NominalMotion",
    "PassEntry",
    "Setup",
    "SampleManifest",
]

MANIFEST_SCHEMA_VERSION = "1.0"

Treatment = Literal["as-welded", "hfmi-treated", "burr-ground"]
_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"


def _check_relative_file(value: str) -> str:
    path = PurePosixPath(value)
    if "\\" in value or path.is_absolute() or value.startswith("~"):
        raise ValueError(f"pass file {value!r} must be a relative POSIX path inside the sample folder")
    if any(part == ".." for part in path.parts) or not path.parts:
        raise ValueError(f"pass file {value!r} must not leave the sample folder ('..' is not allowed)")
    return value


RelativeFile = Annotated[str, AfterValidator(_check_relative_file)]


class SpecimenGeometry(StrictModel):
    """Nominal (drawing) geometry of a dog-bone specimen; the specimen frame has its origin at
    the centre, x along the length, y across the width, z through the thickness."""

    kind: Literal["dog-bone"] = "dog-bone"
    length_mm: float = Field(gt=0, le=5000)
    grip_width_mm: float = Field(gt=0, le=2000)
    gauge_width_mm: float = Field(gt=0, le=2000)
    gauge_length_mm: float = Field(ge=0, le=5000)
    transition_radius_mm: float = Field(gt=0, le=5000)
    thickness_mm: float = Field(gt=0, le=500)

    @model_validator(mode="after")
    def _in_millimetres(self) -> "SpecimenGeometry":
        small = {k: v for k, v in (("length_mm", self.length_mm), ("grip_width_mm", self.grip_width_mm),
                                   ("thickness_mm", self.thickness_mm)) if v < 1.0}
        if small:
            raise ValueError(f"{', '.join(f'{k} {v:g}' for k, v in small.items())}: under 1 mm, not a part a "
                             "scanning cell measures; were the dimensions given in metres? expected millimetres")
        return self


class WeldDescription(StrictModel):
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
    pass_id: str = Field(pattern=_ID_PATTERN)
    file: RelativeFile
    direction: Literal["along-length", "along-width"]
    n_profiles: int = Field(gt=0, le=10_000_000)
    duration_s: float = Field(gt=0)
    nominal_motion: NominalMotion
    has_profile_poses: bool = Field(description="the pass file holds the robot's flange pose per profile")
    content_sha256: str | None = Field(default=None, pattern=r"^[0-9a-f]{64}$")


class Setup(StrictModel):
    """One placement of the specimen in the cell; the robot frame ('world') is the cell's.

    ``T_world_specimen_nominal``: where the fixture puts the specimen frame in this setup, as
    drawn (optional); the specimen lies within ``placement_tolerance_mm`` of it at its weld line.
    With it, the reconstruction knows roughly where the weld is before it has seen the weld and
    keeps that zone at full resolution."""

    name: str = Field(pattern=_ID_PATTERN)
    description: str = ""
    passes: list[PassEntry] = Field(min_length=1)
    T_world_specimen_nominal: Pose4x4 | None = None
    placement_tolerance_mm: float = Field(default=0.0, ge=0, le=1000, description=(
        "how far the specimen's weld line may lie from where T_world_specimen_nominal puts it"))


class SampleManifest(StrictModel):
    schema_version: Literal["1.0"]  # required: a file of another version is told apart, never guessed
    units: Literal["mm"]
    sample_id: str = Field(pattern=_ID_PATTERN)
    created: datetime
    material: str = "S355"
    specimen: SpecimenGeometry
    weld: WeldDescription
    sticker_diameter_mm: float = Field(gt=0, le=100)
    scanner: ScannerSettings
    setups: list[Setup] = Field(min_length=1)

    @field_validator("created")
    @classmethod
    def _timezone_aware(cls, value: datetime) -> datetime:
        if value.tzinfo is None:
            raise ValueError("created must carry a timezone (e.g. 2026-11-22T10:00:00+00:00)")
        return value

    @model_validator(mode="after")
    def _unique_names(self) -> "SampleManifest":
        setups = [s.name for s in self.setups]
        if len(set(setups)) != len(setups):
            raise ValueError(f"setup names must be unique, got {setups}")
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

    def passes(self) -> list[tuple[str, PassEntry]]:
        """All passes as ``(setup_name, entry)`` in manifest order."""
        return [(s.name, p) for s in self.setups for p in s.passes]

    def grid_pitch_mm(self, entry: PassEntry) -> tuple[float, float]:
        """The nominal spacing of a pass's organized grid, mm: between profiles (the sweep's speed
        over the profile rate) and between columns (the scanner's spacing at its reference distance)."""
        motion = entry.nominal_motion
        return motion.speed_mm_s / motion.profile_rate_hz, self.scanner.x_spacing_mm
