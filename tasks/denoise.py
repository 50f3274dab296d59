"""Statistical outlier removal (Rusu et al. 2008) on an organized pass.

A point whose mean distance to its k nearest neighbours exceeds the global mean of that figure
plus ``alpha`` standard deviations is removed. The pass is an organized grid (profiles x
columns), so a point's neighbour candidates are the points in a small window around its cell:
no k-d tree is needed, and the work is linear in the number of points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["DenoiseResult", "remove_statistical_outliers"]


@dataclass(frozen=True)
class DenoiseResult:
    """``keep`` (profiles, columns) bool: a valid point that passed; ``mean_distance_mm`` its
    mean distance to its k nearest window neighbours (NaN where undefined); the threshold used."""

    keep: np.ndarray
    mean_distance_mm: np.ndarray
    threshold_mm: float

    @property
    def n_removed(self) -> int:
        return int(np.count_nonzero(np.isfinite(self.mean_distance_mm) & ~self.keep))


def _mean_knn_distance(points: np.ndarray, valid: np.ndarray, k: int, rows: int, cols: int) -> np.ndarray:
    h, w, _ = points.shape
    padded = np.full((h + 2 * rows, w + 2 * cols, 3), np.nan, dtype=points.dtype)
    padded[rows:rows + h, cols:cols + w] = np.where(valid[..., None], points, np.nan)
    distances = []
    for dr in range(-rows, rows + 1):
        for dc in range(-cols, cols + 1):
            if dr == 0 and dc == 0:
                continue
            shifted = padded[rows + dr:rows + dr + h, cols + dc:cols + dc + w]
            distances.append(np.linalg.norm(shifted - points, axis=-1))
    d = np.stack(distances)  # (window - 1, h, w), NaN where no neighbour
    d = np.where(np.isnan(d), np.inf, d)
    nearest = np.partition(d, k - 1, axis=0)[:k]
    mean = nearest.mean(axis=0)
    mean[~valid | ~np.isfinite(mean)] = np.nan  # fewer than k neighbours in the window
    return mean


def remove_statistical_outliers(points_mm: np.ndarray, *, k: int, alpha: float, window_rows: int,
                                window_cols: int) -> DenoiseResult:
    """Flag outliers of an organized cloud.

    points_mm : (profiles, columns, 3) float, mm, any frame; NaN rows of 3 mark missing returns.
    k : neighbours per point, from the (2*window_rows+1) x (2*window_cols+1) window around it.
    alpha : how many standard deviations above the mean a point's mean distance may lie.

    A point with fewer than k neighbours in its window is removed (isolated).
    """
    points = np.asarray(points_mm)
    if points.ndim != 3 or points.shape[2] != 3:
        raise ValueError(f"points_mm must have shape (profiles, columns, 3), got {points.shape}")
    if k < 1:
        raise ValueError(f"k must be at least 1, got {k}")
    if window_rows < 0 or window_cols < 0 or (2 * window_rows + 1) * (2 * window_cols + 1) - 1 < k:
        raise ValueError(f"a {2 * window_rows + 1} x {2 * window_cols + 1} window holds fewer than k = {k} neighbours")
    if not alpha > 0:
        raise ValueError(f"alpha must be positive, got {alpha}")
    valid = np.isfinite(points).all(axis=2)
    mean = _mean_knn_distance(points.astype(np.float64), valid, k, window_rows, window_cols)
    defined = np.isfinite(mean)
    if not defined.any():
        return DenoiseResult(keep=np.zeros(valid.shape, bool), mean_distance_mm=mean, threshold_mm=float("nan"))
    threshold = float(mean[defined].mean() + alpha * mean[defined].std())
    keep = defined & (mean <= threshold)
    return DenoiseResult(keep=keep, mean_distance_mm=mean, threshold_mm=threshold)
