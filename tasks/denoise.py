"""Statistical outlier removal (Rusu et al. 2008) on an organized pass, in blocks of profiles.

A point whose mean distance to its k nearest neighbours exceeds the global mean of that figure
plus ``alpha`` standard deviations is removed. The pass is an organized grid (profiles x
columns), so a point's neighbour candidates are the points in a small window around its cell:
no k-d tree is needed, and the work is linear in the number of points.

The figure of each point depends on its window only, so a pass can be processed in blocks of
profiles (each with ``window_rows`` halo rows): ``mean_knn_distance`` on each block, the global
statistics accumulated with ``DistanceStats`` (exact integer sums, so the threshold is the same
bytes whatever the blocking), then ``DistanceStats.threshold_mm``. ``remove_statistical_outliers``
does all of it for a whole grid in memory.

The kernels are compiled with Numba (one loop over points, several threads, each point written by
one thread only: the same bytes for any thread count).
"""

from __future__ import annotations

from dataclasses import dataclass

from tasks.kernels import numba
import numpy as np

__all__ = ["DenoiseResult", "DistanceStats", "check_window", "mean_knn_distance", "mean_neighbour_distance", "remove_statistical_outliers",
           "window_offsets"]

# Statistics are summed on distances quantised to this step (mm), in integers: exact, so the mean
# and standard deviation do not depend on the order or the blocks the points come in.
_QUANTUM_MM = 1e-6
_QUANTUM_MAX = 1 << 26  # 67 mm: larger window distances are clipped for the statistics only


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


@dataclass
class DistanceStats:
    """Running count, sum and sum of squares of mean kNN distances, in exact integers."""

    n: int = 0
    s1: int = 0
    s2: int = 0

    def add(self, mean_distance_mm: np.ndarray) -> None:
        """Add the defined (finite) values of ``mean_distance_mm`` (any shape, mm)."""
        n, s1, s2 = _quantised_sums(np.ascontiguousarray(mean_distance_mm, dtype=np.float64).reshape(-1))
        self.n += int(n)
        self.s1 += sum(int(v) for v in s1)
        self.s2 += sum(int(v) for v in s2)

    def threshold_mm(self, alpha: float) -> float:
        """mean + alpha * (population) standard deviation, mm; NaN when nothing was added."""
        if self.n == 0:
            return float("nan")
        mean_q = self.s1 / self.n
        var_q = max(self.s2 * self.n - self.s1 * self.s1, 0) / (self.n * self.n)
        return float((mean_q + alpha * var_q ** 0.5) * _QUANTUM_MM)


@numba.njit(cache=True)
def _quantised_sums(values):
    # per-chunk int64 sums (256 values of at most 2**26, squared 2**52: never overflows), summed
    # exactly in Python integers by the caller
    chunk = 256
    m = (len(values) + chunk - 1) // chunk
    s1 = np.zeros(max(m, 1), np.int64)
    s2 = np.zeros(max(m, 1), np.int64)
    n = 0
    for i in range(len(values)):
        v = values[i]
        if np.isfinite(v):
            q = np.int64(min(np.floor(v / _QUANTUM_MM + 0.5), _QUANTUM_MAX))
            s1[i // chunk] += q
            s2[i // chunk] += q * q
            n += 1
    return n, s1, s2


@numba.njit(parallel=True, cache=True)
def _knn_kernel(points, row0, row1, k, offset_rows, offset_cols, out):
    # the window's offsets come nearest first (by the grid's nominal pitch): the k nearest so far
    # are then found early, and most later candidates fail one comparison with the kth
    h, w = points.shape[0], points.shape[1]
    m = len(offset_rows)
    for i in numba.prange(row0, row1):
        best = np.empty(k)  # squared distances of the k nearest so far, ascending
        for j in range(w):
            px, py, pz = points[i, j, 0], points[i, j, 1], points[i, j, 2]
            if not (np.isfinite(px) and np.isfinite(py) and np.isfinite(pz)):
                out[i - row0, j] = np.nan
                continue
            found = 0
            kth = np.inf
            for o in range(m):
                r = i + offset_rows[o]
                c = j + offset_cols[o]
                if r < 0 or r >= h or c < 0 or c >= w:
                    continue
                dx = points[r, c, 0] - px
                dy = points[r, c, 1] - py
                dz = points[r, c, 2] - pz
                d2 = dx * dx + dy * dy + dz * dz
                if d2 < kth:  # False for a missing neighbour (NaN)
                    pos = found if found < k else k - 1
                    while pos > 0 and best[pos - 1] > d2:
                        best[pos] = best[pos - 1]
                        pos -= 1
                    best[pos] = d2
                    if found < k:
                        found += 1
                    if found == k:
                        kth = best[k - 1]
            if found < k:
                out[i - row0, j] = np.nan
            else:
                s = 0.0
                for q in range(k):
                    s += np.sqrt(best[q])
                out[i - row0, j] = s / k


def window_offsets(window_rows: int, window_cols: int, pitch_mm: tuple[float, float] = (1.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """The (row, column) offsets of a window's neighbours, nearest first on a grid of ``pitch_mm``
    (between rows, between columns); ties in a fixed order. The order changes only the speed of
    ``mean_knn_distance``, never its result."""
    offsets = [(dr, dc) for dr in range(-window_rows, window_rows + 1) for dc in range(-window_cols, window_cols + 1)
               if (dr, dc) != (0, 0)]
    offsets.sort(key=lambda o: ((o[0] * pitch_mm[0]) ** 2 + (o[1] * pitch_mm[1]) ** 2, o))
    return np.array([o[0] for o in offsets], np.int64), np.array([o[1] for o in offsets], np.int64)


def check_window(*, k: int, window_rows: int, window_cols: int) -> None:
    if k < 1:
        raise ValueError(f"k must be at least 1, got {k}")
    if window_rows < 0 or window_cols < 0 or (2 * window_rows + 1) * (2 * window_cols + 1) - 1 < k:
        raise ValueError(f"a {2 * window_rows + 1} x {2 * window_cols + 1} window holds fewer than k = {k} neighbours")


def mean_knn_distance(points_mm: np.ndarray, *, k: int, window_rows: int, window_cols: int,
                      rows: slice | None = None, pitch_mm: tuple[float, float] = (1.0, 1.0)) -> np.ndarray:
    """Each point's mean distance to its k nearest neighbours in its window, mm.

    points_mm : (profiles, columns, 3) float, mm, any frame; NaN marks a missing return. For a
        block of a pass, the block's rows with ``window_rows`` halo rows on each side.
    rows : the rows to compute (default all): the block's own rows when halo rows are included.
    pitch_mm : the grid's nominal pitch (between rows, between columns): neighbours are tried
        nearest first, which is faster; the result does not depend on it.
    Returns (len(rows), columns) float64; NaN where the point is missing or has fewer than k
    neighbours in its (2*window_rows+1) x (2*window_cols+1) window (sorted sum of the k smallest
    distances over k: the same bytes for any blocking or thread count).
    """
    points = np.asarray(points_mm, dtype=np.float64)
    if points.ndim != 3 or points.shape[2] != 3:
        raise ValueError(f"points_mm must have shape (profiles, columns, 3), got {points.shape}")
    check_window(k=k, window_rows=window_rows, window_cols=window_cols)
    start, stop, _ = (rows or slice(None)).indices(points.shape[0])
    out = np.empty((max(stop - start, 0), points.shape[1]))
    offset_rows, offset_cols = window_offsets(int(window_rows), int(window_cols), pitch_mm)
    _knn_kernel(np.ascontiguousarray(points), start, stop, int(k), offset_rows, offset_cols, out)
    return out


def remove_statistical_outliers(points_mm: np.ndarray, *, k: int, alpha: float, window_rows: int,
                                window_cols: int, pitch_mm: tuple[float, float] = (1.0, 1.0)) -> DenoiseResult:
    """Flag outliers of an organized cloud held whole (the blocks of a pass give the same result).

    points_mm : (profiles, columns, 3) float, mm, any frame; NaN rows of 3 mark missing returns.
    k : neighbours per point, from the (2*window_rows+1) x (2*window_cols+1) window around it.
    alpha : how many standard deviations above the mean a point's mean distance may lie.

    A point with fewer than k neighbours in its window is removed (isolated).
    """
    if not alpha > 0:
        raise ValueError(f"alpha must be positive, got {alpha}")
    mean = mean_knn_distance(points_mm, k=k, window_rows=window_rows, window_cols=window_cols, pitch_mm=pitch_mm)
    stats = DistanceStats()
    stats.add(mean)
    threshold = stats.threshold_mm(alpha)
    keep = np.isfinite(mean) & (mean <= threshold)
    return DenoiseResult(keep=keep, mean_distance_mm=mean, threshold_mm=threshold)


def mean_neighbour_distance(points_mm: np.ndarray, *, k: int) -> np.ndarray:
    """Each point's mean distance to its ``k`` nearest other points, for a cloud without a grid
    (an imported scan): ``points_mm`` (n, 3) finite, mm -> (n,) float64, mm; NaN for every point
    when the cloud has k points or fewer. One-worker k-d tree queries: the same bytes on every run."""
    found = _nearest(points_mm, k)
    if found is None:
        return np.full(len(points_mm), np.nan)
    return found[0].mean(axis=1)


def _nearest(points_mm: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Each point's distances to its ``k`` nearest other points and their indices, (n, k) each
    (one-worker k-d tree queries); None when the cloud has k points or fewer."""
    from scipy.spatial import cKDTree

    from tasks.checks import check_points

    pts = check_points("points_mm", points_mm)
    if not isinstance(k, (int, np.integer)) or k < 1:
        raise ValueError(f"k must be an integer >= 1, got {k!r}")
    if len(pts) <= k:
        return None
    distances, index = cKDTree(pts).query(pts, k=k + 1, workers=1)
    return distances[:, 1:], index[:, 1:]


def relative_neighbour_distance(points_mm: np.ndarray, *, k: int) -> np.ndarray:
    """Each point's mean distance to its ``k`` nearest other points over the median of theirs
    (dimensionless; NaN as ``mean_neighbour_distance``): the statistical outlier test of a cloud
    whose spacing changes over it. A line scanner's points lie 0.05 mm apart along a profile and
    0.2-0.5 mm between profiles, further apart on a steep flank than on the plate; on the plain
    distance the flank is what lies beyond mean + alpha sigma (measured: 11 % of a 45 deg butt
    weld's points at 0.25 mm between profiles, its flank angle then read 7 deg low), on this ratio
    a point off the surface among its neighbours on it."""
    found = _nearest(points_mm, k)
    if found is None:
        return np.full(len(points_mm), np.nan)
    distances, index = found
    mean = distances.mean(axis=1)
    around = np.median(mean[index], axis=1)
    return mean / np.maximum(around, np.finfo(np.float64).tiny)
