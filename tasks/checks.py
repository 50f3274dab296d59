"""Input checks shared by the stage modules."""

from __future__ import annotations

import numpy as np

__all__ = ["check_points"]


def check_points(name: str, values, n: int | None = None) -> np.ndarray:
    """``values`` as a finite (n, 3) float64 array; ValueError naming ``name`` otherwise. With
    ``n`` given, the array must have exactly n rows (one per point)."""
    array = np.asarray(values, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"{name} must have shape (n, 3), got {array.shape}")
    if n is not None and len(array) != n:
        raise ValueError(f"{name} must have one row per point ({n}), got {len(array)}")
    if not np.isfinite(array).all():
        raise ValueError(f"{name} holds NaN or inf")
    return array
