"""Fatigue life from a notch stress range by an IIW S-N curve (Hobbacher, IIW recommendations for
fatigue design of welded joints and components): ``FAT`` the stress range at 2 million cycles,
the curve's slope up to the knee at 1e7 cycles (constant amplitude) and 22 beyond. Numbers in,
numbers out."""

from __future__ import annotations

__all__ = ["notch_cycles", "KNEE_CYCLES", "SLOPE_BEYOND_KNEE"]

KNEE_CYCLES = 1e7
SLOPE_BEYOND_KNEE = 22.0


def notch_cycles(notch_range_mpa: float, fat_mpa: float, slope: float) -> float:
    """Cycles to failure at ``notch_range_mpa``: 2e6 (FAT / range)^slope up to 1e7 cycles, the
    slope 22 beyond."""
    if not (notch_range_mpa > 0 and fat_mpa > 0 and slope > 0):
        raise ValueError(f"the stress range, FAT and slope must be positive, got {notch_range_mpa}, {fat_mpa}, {slope}")
    cycles = 2e6 * (fat_mpa / notch_range_mpa) ** slope
    if cycles <= KNEE_CYCLES:
        return cycles
    knee = fat_mpa * (2e6 / KNEE_CYCLES) ** (1 / slope)
    return KNEE_CYCLES * (knee / notch_range_mpa) ** SLOPE_BEYOND_KNEE
