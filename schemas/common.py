"""Building blocks shared by every schema: a strict base model, rigid poses, value ranges."""

from __future__ import annotations

import math
from datetime import datetime
from typing import Annotated

from pydantic import AfterValidator, BaseModel, ConfigDict

__all__ = ["StrictModel", "InputModel", "Pose4x4", "Vector3", "FloatRange", "AwareDatetime", "check_rigid_pose", "without_none"]

_ROTATION_TOLERANCE = 1e-6


class StrictModel(BaseModel):
    """Base of every weldrecon schema: unknown fields are errors, instances are immutable."""

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True)


class InputModel(StrictModel):
    """A StrictModel a person writes (settings, acceptance limits, a cell's description): no NaN or
    infinity in any number (a limit of ``.inf`` or a time offset of ``.nan`` is a typo, never a
    setting; pydantic names the field)."""

    model_config = ConfigDict(allow_inf_nan=False)


def check_rigid_pose(value: list[list[float]]) -> list[list[float]]:
    """Check that ``value`` is a finite 4x4 homogeneous rigid transform (mm); return it unchanged."""
    if len(value) != 4 or any(len(row) != 4 for row in value):
        raise ValueError("a pose must be a 4x4 matrix (list of 4 rows of 4 numbers)")
    if not all(math.isfinite(v) for row in value for v in row):
        raise ValueError("a pose must contain only finite numbers (found NaN or inf)")
    if [abs(v) for v in value[3][:3]] != [0.0, 0.0, 0.0] or value[3][3] != 1.0:
        raise ValueError("the last row of a pose must be [0, 0, 0, 1]")
    rot = [row[:3] for row in value[:3]]
    for i in range(3):
        for j in range(3):
            dot = sum(rot[k][i] * rot[k][j] for k in range(3))
            if abs(dot - (1.0 if i == j else 0.0)) > _ROTATION_TOLERANCE:
                raise ValueError("the rotation part of a pose must be orthonormal")
    det = (
        rot[0][0] * (rot[1][1] * rot[2][2] - rot[1][2] * rot[2][1])
        - rot[0][1] * (rot[1][0] * rot[2][2] - rot[1][2] * rot[2][0])
        + rot[0][2] * (rot[1][0] * rot[2][1] - rot[1][1] * rot[2][0])
    )
    if det < 0:
        raise ValueError("the rotation part of a pose must have determinant +1 (no reflection)")
    return value


def _check_finite_vector(value: tuple[float, float, float]) -> tuple[float, float, float]:
    if not all(math.isfinite(v) for v in value):
        raise ValueError("a vector must contain only finite numbers")
    return value


def _check_range(value: tuple[float, float]) -> tuple[float, float]:
    low, high = value
    if not (math.isfinite(low) and math.isfinite(high)):
        raise ValueError("range bounds must be finite")
    if low > high:
        raise ValueError(f"range low bound {low} exceeds high bound {high}")
    return value


Pose4x4 = Annotated[list[list[float]], AfterValidator(check_rigid_pose)]
"""A rigid transform as a 4x4 row-major matrix; translation in mm. Named ``T_<to>_<from>``."""

Vector3 = Annotated[tuple[float, float, float], AfterValidator(_check_finite_vector)]

FloatRange = Annotated[tuple[float, float], AfterValidator(_check_range)]
"""A closed interval ``(low, high)`` from which the simulator draws a value."""


def _timezone_aware(value: datetime) -> datetime:
    if value.tzinfo is None:
        raise ValueError("must carry a timezone (e.g. 2026-11-22T10:00:00+00:00)")
    return value


# a time that says which time it is: a naive one is refused
AwareDatetime = Annotated[datetime, AfterValidator(_timezone_aware)]


def without_none(data: dict, *keys: str) -> dict:
    """``data`` (a model's dump) with each of ``keys`` left out where it is None: a field added
    later, written as before it when not given."""
    for key in keys:
        if key in data and data[key] is None:
            del data[key]
    return data

