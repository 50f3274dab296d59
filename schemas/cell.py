"""A real cell's logs described for ``weldrecon import``: the ``CELL.yaml`` next to the files a
lab's robot and line scanner write, one profile file and one pose log per pass.

The sample fields (specimen, weld, scanner with its hand-eye ``T_flange_sensor``) are the
manifest's own (``schemas.manifest``); what is new here is how the files are written: the profile
file's layout, delimiter, units, clock and no-return marker, and the pose log's columns, units and
rotation convention. The format is described in ``docs/cell-logs.md``.
"""

from __future__ import annotations

import re
from pathlib import PurePosixPath
from typing import Literal

from pydantic import AfterValidator, Field, model_validator
from typing_extensions import Annotated

from schemas.common import AwareDatetime, InputModel, Pose4x4
from schemas.manifest import _ID_PATTERN, ScannerSettings, SpecimenGeometry, WeldDescription

__all__ = ["ROTATION_CONVENTIONS", "EULER_PATTERN", "orientation_columns", "scipy_euler_sequence", "XGrid",
           "ProfileFormat", "PoseLogFormat", "CellPass", "CellSetup", "CellDescription"]

ROTATION_CONVENTIONS = {
    "quaternion": "unit quaternion, columns qw qx qy qz in the file's order (wxyz or xyzw; ABB's q1..q4 = wxyz)",
    "rotation-vector": "axis times angle, columns rx ry rz (angle_unit rad or deg; Universal Robots: rad)",
    "kuka-abc": "KUKA A, B, C in degrees: R = Rz(A) Ry(B) Rx(C) (intrinsic Z, Y', X'')",
    "fanuc-wpr": "Fanuc W, P, R in degrees: R = Rz(R) Ry(P) Rx(W) (about the fixed X, then Y, then Z)",
    "euler-<AXES>-<intrinsic|extrinsic>": "three angles e1 e2 e3 about the axes in that order, e.g. "
                                          "euler-ZYX-intrinsic, euler-xyz-extrinsic (angle_unit rad or deg)",
}
"""The pose log's rotation conventions, by name (``PoseLogFormat.orientation``)."""

EULER_PATTERN = re.compile(r"^euler-(?P<axes>[xyzXYZ]{3})-(?P<kind>intrinsic|extrinsic)$")

_FIXED_EULER = {"kuka-abc": ("ZYX", ("a", "b", "c")), "fanuc-wpr": ("xyz", ("w", "p", "r"))}


def _euler_axes_valid(axes: str) -> bool:
    return axes[0] != axes[1] and axes[1] != axes[2]


def scipy_euler_sequence(orientation: str) -> str | None:
    """The ``scipy.spatial.transform.Rotation.from_euler`` sequence of an Euler convention
    (upper case: intrinsic, lower case: extrinsic), in the order of its columns; None for a
    quaternion or rotation vector."""
    if orientation in _FIXED_EULER:
        return _FIXED_EULER[orientation][0]
    match = EULER_PATTERN.match(orientation)
    if match is None:
        return None
    axes = match["axes"]
    return axes.upper() if match["kind"] == "intrinsic" else axes.lower()


def orientation_columns(orientation: str) -> tuple[str, ...]:
    """The pose log's column names that carry the rotation of ``orientation`` (any order in the file)."""
    if orientation == "quaternion":
        return ("qw", "qx", "qy", "qz")
    if orientation == "rotation-vector":
        return ("rx", "ry", "rz")
    if orientation in _FIXED_EULER:
        return _FIXED_EULER[orientation][1]
    return ("e1", "e2", "e3")


def _check_orientation(value: str) -> str:
    if value in ROTATION_CONVENTIONS and "<" not in value:
        return value
    match = EULER_PATTERN.match(value)
    if match and _euler_axes_valid(match["axes"]):
        return value
    known = "; ".join(f"{name}: {what}" for name, what in ROTATION_CONVENTIONS.items())
    raise ValueError(f"unknown rotation convention {value!r}; known: {known}")


def _check_relative(value: str) -> str:
    if not value or PurePosixPath(value).is_absolute() or "\\" in value or value.startswith("~"):
        raise ValueError(f"{value!r}: expected a relative POSIX path (resolved against the CELL.yaml's folder)")
    if ".." in PurePosixPath(value).parts:
        raise ValueError(f"{value!r} climbs out of the CELL.yaml's folder ('..'); expected a path inside it")
    return value


LogFile = Annotated[str, AfterValidator(_check_relative)]


class XGrid(InputModel):
    """The fixed X positions of a ``z_grid`` profile, mm, sensor frame S: point i at
    ``x0_mm + i * spacing_mm``; without ``x0_mm`` the grid is centred on S's z axis
    (``x0_mm = -(points_per_profile - 1) / 2 * spacing_mm``)."""

    spacing_mm: float = Field(gt=0, le=10)
    x0_mm: float | None = None


class ProfileFormat(InputModel):
    """How the scanner's profile file is written: one profile per line.

    ``xzi``: the profile's time, then X, Z, intensity for each of the scanner's
    ``points_per_profile`` points. ``z_grid``: the time, then Z for each point on the fixed X
    grid ``x_grid`` (followed by one intensity per point when ``intensities``). A point whose X or
    Z is ``no_return`` (``nan``, ``empty``: an empty CSV field, or a number such as ``0`` or
    ``-9999``, compared before the units are applied) is no return. A name ending in ``.gz`` is
    gzip-compressed."""

    layout: Literal["xzi", "z_grid"]
    delimiter: Literal["csv", "whitespace"]
    units: Literal["mm", "m"]
    time_unit: Literal["s", "ms"]
    no_return: Literal["nan", "empty"] | float = "nan"
    header_lines: int = Field(default=0, ge=0, le=1000, description="lines before the first profile")
    intensity_bits: int = Field(default=10, ge=1, le=16, description="the file's intensities are 0..2^bits-1; "
                                "rescaled to the pass format's 10 bits")
    x_grid: XGrid | None = Field(default=None, description="z_grid only: the X of each point")
    intensities: bool = Field(default=True, description="z_grid only: one intensity per point after the Z values")

    @model_validator(mode="after")
    def _layout_fields(self) -> "ProfileFormat":
        if (self.layout == "z_grid") != (self.x_grid is not None):
            raise ValueError("x_grid is required with layout z_grid and not allowed with layout xzi")
        if self.layout == "xzi" and not self.intensities:
            raise ValueError("intensities false applies to layout z_grid only (xzi always carries them)")
        if self.no_return == "empty" and self.delimiter != "csv":
            raise ValueError("no_return 'empty' needs delimiter csv (whitespace cannot hold an empty field)")
        return self


class PoseLogFormat(InputModel):
    """How the robot's pose log is written: one pose per line, ``columns`` naming each column
    in the file's order: ``time``, ``x``, ``y``, ``z`` (the position) and the rotation's columns
    (``orientation_columns``); ``pose_of`` says whether the pose is the flange's or the TCP's."""

    columns: list[str] = Field(min_length=7)
    delimiter: Literal["csv", "whitespace"]
    units: Literal["mm", "m"]
    time_unit: Literal["s", "ms"]
    orientation: Annotated[str, AfterValidator(_check_orientation)]
    angle_unit: Literal["deg", "rad"] | None = Field(default=None, description=(
        "rotation-vector and euler-*: required; kuka-abc and fanuc-wpr are degrees"))
    header_lines: int = Field(default=0, ge=0, le=1000)
    pose_of: Literal["flange", "tcp"] = "flange"

    @model_validator(mode="after")
    def _columns_match(self) -> "PoseLogFormat":
        wanted = ("time", "x", "y", "z", *orientation_columns(self.orientation))
        if sorted(self.columns) != sorted(wanted):
            raise ValueError(f"columns {self.columns} must name each of {', '.join(wanted)} once "
                             f"(orientation {self.orientation})")
        fixed = self.orientation in _FIXED_EULER
        if fixed and self.angle_unit not in (None, "deg"):
            raise ValueError(f"{self.orientation} angles are degrees; angle_unit must be deg or left out")
        if self.orientation != "quaternion" and not fixed and self.angle_unit is None:
            raise ValueError(f"angle_unit (deg or rad) is required with orientation {self.orientation}")
        return self


class CellPass(InputModel):
    pass_id: str = Field(pattern=_ID_PATTERN)
    profiles: LogFile
    poses: LogFile
    direction: str = Field(min_length=1, max_length=64, pattern=r"\S")


class CellSetup(InputModel):
    """One placement of the specimen (as in ``schemas.manifest.Setup``), its passes' log files."""

    name: str = Field(pattern=_ID_PATTERN)
    description: str = ""
    passes: list[CellPass] = Field(min_length=1)
    T_world_specimen_nominal: Pose4x4 | None = None
    placement_tolerance_mm: float = Field(default=0.0, ge=0, le=1000)


class CellDescription(InputModel):
    """``CELL.yaml``: the sample and how its cell wrote its logs. ``time_offset_s``: added to a
    profile's time (the scanner's clock, s) to give the robot clock's time of the same instant.
    ``T_flange_tcp``: the TCP in the flange frame, required when the pose log gives the TCP's
    pose (``T_world_flange = T_world_tcp @ inv(T_flange_tcp)``)."""

    sample_id: str = Field(pattern=_ID_PATTERN)
    created: AwareDatetime
    material: str = "S355"
    specimen: SpecimenGeometry
    weld: WeldDescription
    sticker_diameter_mm: float = Field(gt=0, le=100)
    scanner: ScannerSettings
    profile_format: ProfileFormat
    pose_format: PoseLogFormat
    time_offset_s: float = 0.0
    T_flange_tcp: Pose4x4 | None = None
    setups: list[CellSetup] = Field(min_length=1)

    @model_validator(mode="after")
    def _consistent(self) -> "CellDescription":
        if (self.pose_format.pose_of == "tcp") != (self.T_flange_tcp is not None):
            raise ValueError("T_flange_tcp is required when pose_format.pose_of is tcp, and not allowed otherwise")
        ids = [p.pass_id for s in self.setups for p in s.passes]
        dupes = sorted({i for i in ids if ids.count(i) > 1})
        if dupes:
            raise ValueError(f"pass ids must be unique across setups, repeated: {dupes}")
        names = [s.name for s in self.setups]
        if len(set(names)) != len(names):
            raise ValueError(f"setup names must be unique, got {names}")
        first: dict[str, str] = {}
        for s in self.setups:
            for p in s.passes:
                key = str(PurePosixPath(p.profiles))
                if key in first:  # one sweep's profiles read twice, as two passes: never a scan
                    raise ValueError(f"pass {p.pass_id} names the profile file {p.profiles!r} of pass {first[key]}; "
                                     "expected each pass its own profile file")
                first[key] = p.pass_id
        return self
