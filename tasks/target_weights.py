"""Each sticker target centre's expected error, from its own rim fit (``tasks.targets``), for the
pose refinement's target pairs (``tasks.refine.refine_poses``'s ``target_sigma_mm``).

1. The rim fit's RMS, times a factor, at least a floor: how well the edge points fit a circle.
2. The edge height the fit found with the centre. The stickers of a sample are one paper, so
   their heights agree to what the fits allow; a fit whose height is off the sample's median by
   more than ``gate`` times its expected spread has traded height for centre along its own valley
   (the centre moves ``centre_per_height`` mm per mm of height, from the fit's covariance), and its
   sigma grows by ``height_factor`` x that move for the height's distance from the median: an
   estimate of its centre's error if the true height is the median's.

   The expected spread is the fit's own height sigma and the heights' unexplained scatter
   together: the sample's robust spread (1.4826 x the median absolute deviation) less what the
   fits' own sigmas explain (their median), in quadrature. Where the profiles are 0.3-0.5 mm apart
   (ci, the T-joints) the fits' own sigmas explain the spread (0.84-1.1 of it) and the gate finds
   the fits that went astray: a T-joint's one detection 80 um off, at the height's bound of 0.3 mm.
   At the sensor's full resolution the fits are precise and their heights are not one paper's:
   on the paper preset the median fit finds 0.024 mm, spread 0.021, own sigma 0.006 (the paper is
   0.1 mm; the height there absorbs what else the edge model leaves), and gating on them spoilt the
   worst pass 5.8 -> 13.6 um. So the heights are used only where their spread is at most
   ``max_spread_ratio`` x the fits' own sigma (``HeightSpread.consistent``).
   Measured on each preset's stored stages: bench/README.md, "What the targets' error is".
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["HeightSpread", "height_spread", "centre_sigmas"]

_MAD_TO_SIGMA = 1.4826  # a normal distribution's sigma per median absolute deviation


@dataclass(frozen=True)
class HeightSpread:
    """What a sample's rim fits say about their edge heights (mm)."""

    median_mm: float  # the heights' median
    spread_mm: float  # their robust spread (1.4826 x the median absolute deviation)
    own_sigma_mm: float  # the fits' own height sigmas' median
    scatter_mm: float  # the spread the fits' own sigmas leave unexplained (0 where they explain it)

    def consistent(self, max_ratio: float) -> bool:
        """Whether the heights spread no more than ``max_ratio`` x what the fits' own sigmas allow:
        whether they are one sample's measures of one paper edge, worth gating on."""
        return self.spread_mm <= max_ratio * self.own_sigma_mm


def height_spread(height_mm: np.ndarray, height_sigma_mm: np.ndarray) -> HeightSpread:
    """The spread of one sample's fitted edge heights (each target once: (k,) each)."""
    h = np.asarray(height_mm, np.float64)
    s = np.asarray(height_sigma_mm, np.float64)
    if h.shape != s.shape or h.ndim != 1 or len(h) == 0:
        raise ValueError(f"heights and their sigmas must be two equal, non-empty (k,) arrays, "
                         f"got {h.shape} and {s.shape}")
    median = float(np.median(h))
    spread = _MAD_TO_SIGMA * float(np.median(np.abs(h - median)))
    own = float(np.median(s))
    return HeightSpread(median_mm=median, spread_mm=spread, own_sigma_mm=own,
                        scatter_mm=float(np.sqrt(max(0.0, spread * spread - own * own))))


def centre_sigmas(rim_rms_mm: np.ndarray, height_mm: np.ndarray, height_sigma_mm: np.ndarray,
                  centre_per_height: np.ndarray, spread: HeightSpread | None, *, rim_factor: float, floor_mm: float,
                  gate: float | None, height_factor: float, max_spread_ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Each centre's expected error (mm) and whether its height was gated ((k,) each).

    rim_rms_mm, height_mm, height_sigma_mm : (k,) the rim fits' RMS, edge heights and their sigmas.
    centre_per_height : (k,) how far each centre moves per mm of height along its fit's valley.
    spread : the sample's heights (``height_spread``); needed where ``gate`` is given.
    rim_factor, floor_mm : sigma = max(rim_factor x RMS, floor_mm) before the height's term.
    gate : heights off the median by more than this many of their expected spread get the term;
        None: none do.
    height_factor : the term's size per mm of centre move.
    max_spread_ratio : the heights are gated on only where they are consistent
        (``HeightSpread.consistent``); otherwise every centre keeps its rim's term.
    """
    rms = np.asarray(rim_rms_mm, np.float64)
    sigma = np.maximum(rim_factor * rms, floor_mm)
    if gate is None:
        return sigma, np.zeros(len(sigma), bool)
    if spread is None:
        raise ValueError("centre_sigmas: a height gate needs the sample's height spread")
    if not spread.consistent(max_spread_ratio):
        return sigma, np.zeros(len(sigma), bool)
    off = np.abs(np.asarray(height_mm, np.float64) - spread.median_mm)
    expected = np.hypot(np.asarray(height_sigma_mm, np.float64), spread.scatter_mm)
    gated = off > gate * expected
    return sigma + np.where(gated, height_factor * np.abs(np.asarray(centre_per_height, np.float64)) * off, 0.0), gated
