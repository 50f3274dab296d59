"""The search for sticker circles in a pass's intensity image, fed block by block: the grid's
point spacing (``GridSpacing``, from a fixed sample of profiles), the search's pixel and window
sizes (``search_grid``), the intensity resampled to square pixels (``HoughImage``, built row by row
with weights fixed by global indices, so any blocking gives the same bytes) and OpenCV's Hough
transform on it (``find_circles``). ``tasks.targets`` refines each circle found to a 3-D centre.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["GridSpacing", "SearchGrid", "HoughImage", "search_grid", "find_circles"]

_SPACING_STRIDE = 16  # GridSpacing samples every 16th profile ...
_SPACING_PROFILES = 128  # ... or fewer, at most this many


class GridSpacing:
    """The point spacing of a pass's organized grid, mm: the median 3-D distance between
    neighbouring profiles and between neighbouring columns, over a fixed sample of the pass:
    profiles r = 0, s, 2 s, ... (s = 16, or more so that at most 128 profiles are sampled), the
    column neighbours within each and the pairs (r, r + 1). The sample depends on the pass's length
    only, so the pass may be fed in any consecutive runs of profiles (``add``, in order), and what
    is kept does not grow past 128 sampled profiles.

    n_profiles : the pass's number of profiles (>= 1).
    """

    def __init__(self, n_profiles: int) -> None:
        if not (isinstance(n_profiles, (int, np.integer)) and n_profiles >= 1):
            raise ValueError(f"n_profiles must be a positive integer, got {n_profiles!r}")
        self.n_profiles = int(n_profiles)
        self.stride = max(_SPACING_STRIDE, -(-self.n_profiles // _SPACING_PROFILES))
        self._next = 0
        self._rows: list[np.ndarray] = []
        self._cols: list[np.ndarray] = []

    def add(self, points: np.ndarray, *, start: int, stop: int | None = None) -> None:
        """Sample profiles ``start`` to ``stop`` (exclusive; default: all of ``points``), the next
        ones after the previous call's.

        points : (rows, columns, 3) float, mm, NaN missing: the pass's profiles from ``start`` on,
            holding profile ``stop`` too unless ``stop`` is the end of the pass (a sampled profile's
            partner across the profiles).
        """
        points = np.asarray(points)
        stop = start + len(points) if stop is None else stop
        if points.ndim != 3 or points.shape[2] != 3:
            raise ValueError(f"points must be (rows, columns, 3), got shape {points.shape}")
        if start != self._next or not start <= stop <= self.n_profiles:
            raise ValueError(f"profiles {start}:{stop} do not follow profile {self._next} of {self.n_profiles}")
        if len(points) < min(stop + 1, self.n_profiles) - start:
            raise ValueError(f"profiles {start}:{stop}: points hold {len(points)} profiles, "
                             f"{min(stop + 1, self.n_profiles) - start} needed (the next one too)")
        first = -(-start // self.stride) * self.stride
        sampled = np.arange(first, stop, self.stride) - start
        paired = sampled[sampled + start + 1 < self.n_profiles]
        self._cols.append(_distances(np.diff(points[sampled], axis=1)))
        self._rows.append(_distances(points[paired + 1] - points[paired]))
        self._next = stop

    def spacing_mm(self) -> tuple[float, float]:
        """(between profiles, between columns), mm; NaN where the sample holds no pair of points."""
        if self._next != self.n_profiles:
            raise ValueError(f"profiles {self._next}:{self.n_profiles} were never added")
        return _median(self._rows), _median(self._cols)


def _distances(d: np.ndarray) -> np.ndarray:
    """(k,) finite lengths of the (..., 3) differences ``d``."""
    n = np.linalg.norm(d.reshape(-1, 3), axis=-1)
    return n[np.isfinite(n)]


def _median(parts: list[np.ndarray]) -> float:
    values = np.concatenate(parts) if parts else np.zeros(0)
    return float(np.median(values)) if values.size else float("nan")


@dataclass(frozen=True)
class SearchGrid:
    """Where a pass's circles are searched (``search_grid``): its grid of ``shape`` (profiles,
    columns), ``spacing_mm`` (between profiles, between columns) apart, resampled to square pixels
    of ``pixel_mm`` (an image of ``image_shape`` (rows, columns)); the window a circle is refined in
    reaches ``half_rows`` profiles and ``half_cols`` columns either side of its centre (1.6
    sticker radii, plus one)."""

    shape: tuple[int, int]
    spacing_mm: tuple[float, float]
    radius_mm: float
    pixel_mm: float
    image_shape: tuple[int, int]
    half_rows: int
    half_cols: int

    @property
    def radius_px(self) -> float:
        return self.radius_mm / self.pixel_mm

    def grid_position(self, circle: np.ndarray) -> tuple[float, float]:
        """(profile, column) of a Hough circle's centre (x, y image pixels; pixel centres at whole
        numbers both ways): each image pixel is the area mean of the grid cells it covers."""
        (h, w), (rows, cols) = self.shape, self.image_shape
        return (float(circle[1]) + 0.5) * h / rows - 0.5, (float(circle[0]) + 0.5) * w / cols - 0.5

    def centre_row(self, row: float) -> int:
        """The profile a circle at ``row`` (``grid_position``) is refined around, 0..profiles-1."""
        return min(max(int(np.floor(row)), 0), self.shape[0] - 1)

    def window(self, row: float, col: float) -> tuple[slice, slice]:
        """The profiles and columns a circle at (``row``, ``col``) is refined in, inside the grid."""
        (h, w), r = self.shape, self.centre_row(row)
        c = min(max(int(np.floor(col)), 0), w - 1)
        return (slice(max(r - self.half_rows, 0), min(r + self.half_rows + 1, h)),
                slice(max(c - self.half_cols, 0), min(c + self.half_cols + 1, w)))


def search_grid(shape: tuple[int, int], spacing_mm: tuple[float, float], *,
                sticker_diameter_mm: float) -> SearchGrid | None:
    """The search of a pass of ``shape`` (profiles, columns) whose points are ``spacing_mm``
    (between profiles, between columns; ``GridSpacing``) apart: square pixels of the finer spacing,
    but no finer than 1/40 of the sticker's radius. None when a spacing is not finite (too few
    points to measure it)."""
    h, w = (int(n) for n in shape)
    if h < 1 or w < 1:
        raise ValueError(f"shape must be positive (profiles, columns), got {shape}")
    if not sticker_diameter_mm > 0:
        raise ValueError(f"sticker_diameter_mm must be positive, got {sticker_diameter_mm}")
    row_mm, col_mm = (float(s) for s in spacing_mm)
    if not (np.isfinite(row_mm) and np.isfinite(col_mm) and row_mm > 0 and col_mm > 0):
        return None
    radius = sticker_diameter_mm / 2
    pixel = max(min(row_mm, col_mm), radius / 40)
    return SearchGrid(shape=(h, w), spacing_mm=(row_mm, col_mm), radius_mm=radius, pixel_mm=pixel,
                      image_shape=(max(1, int(round(h * row_mm / pixel))), max(1, int(round(w * col_mm / pixel)))),
                      half_rows=int(np.ceil(1.6 * radius / row_mm)) + 1,
                      half_cols=int(np.ceil(1.6 * radius / col_mm)) + 1)


def _area_taps(n_in: int, n_out: int, out: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which input cells each output cell ``out`` (k,) covers and with which weight when ``n_in``
    cells are resampled to ``n_out`` by area (OpenCV's INTER_AREA along one axis): output j spans
    inputs [j n_in / n_out, (j + 1) n_in / n_out). Returns the inputs (k, t) int64 (a covered one
    repeated, weight 0, past the last) and their weights (k, t) float64, from j's global index alone."""
    taps = -(-n_in // n_out) + 1
    first = out * n_in // n_out
    last = ((out + 1) * n_in + n_out - 1) // n_out - 1
    index = first[:, None] + np.arange(taps)
    lo, hi = (out * n_in / n_out)[:, None], ((out + 1) * n_in / n_out)[:, None]
    weight = np.clip(np.minimum(index + 1, hi) - np.maximum(index, lo), 0.0, None) / (hi - lo)
    return np.minimum(index, last[:, None]), weight


def _weighted_sum(values: np.ndarray, index: np.ndarray, weight: np.ndarray, axis: int) -> np.ndarray:
    """sum over t of values.take(index[:, t], axis) * weight[:, t], term by term in t's order: each
    output is the same bytes whatever else is computed with it (no BLAS, no reordering)."""
    shape = [1, 1]
    shape[axis] = len(index)
    out = np.zeros(values.shape[:axis] + (len(index),) + values.shape[axis + 1:])
    for t in range(index.shape[1]):
        out += values.take(index[:, t], axis=axis) * weight[:, t].reshape(shape)
    return out


class HoughImage:
    """The image a pass's circles are searched in (``grid``: ``search_grid``), built from its
    intensity fed in consecutive runs of profiles (``add``). Each pixel is the area-weighted mean
    of intensity / 4 (0..255) over the grid cells it covers, rounded to uint8 (OpenCV's INTER_AREA,
    done separably: along each profile, then across profiles), summed in an order fixed by the
    pixel's own position: any split of the pass gives the same bytes.

    It holds the image (``image_shape`` uint8: the one part of the search that grows with the pass,
    about one byte per 3 points at full resolution: 8401 x 546 = 4.6 MB for 6301 x 2048 points at
    0.1 x 0.02 mm and 6 mm stickers) and the few resampled profiles an unfinished image row needs.
    """

    def __init__(self, grid: SearchGrid) -> None:
        self.grid = grid
        (_, w), (_, cols) = grid.shape, grid.image_shape
        self._col_index, self._col_weight = _area_taps(w, cols, np.arange(cols))
        self._seen = 0  # profiles added
        self._done = 0  # image rows finished
        self._pending = np.zeros((0, cols))  # profiles _pending_start.. resampled along the profile
        self._pending_start = 0
        self._rows: list[np.ndarray] = []

    def add(self, intensity: np.ndarray) -> None:
        """intensity : (rows, columns) uint16, the pass's next profiles (0: no return)."""
        intensity = np.asarray(intensity)
        (h, w), (rows, _) = self.grid.shape, self.grid.image_shape
        if intensity.ndim != 2 or intensity.shape[1] != w or self._seen + len(intensity) > h:
            raise ValueError(f"intensity must be (rows, {w}) with at most {h - self._seen} rows left, "
                             f"got shape {intensity.shape}")
        values = np.minimum(intensity / 4.0, 255.0)
        resampled = _weighted_sum(values, self._col_index, self._col_weight, axis=1)
        self._pending = np.concatenate([self._pending, resampled])
        self._seen += len(intensity)
        ready = self._seen * rows // h  # image rows whose profiles have all been added
        if ready > self._done:
            index, weight = _area_taps(h, rows, np.arange(self._done, ready))
            image_rows = _weighted_sum(self._pending, index - self._pending_start, weight, axis=0)
            self._rows.append(np.clip(np.rint(image_rows), 0, 255).astype(np.uint8))
            self._done = ready
            keep = self._done * h // rows if self._done < rows else h  # the next image row's first profile
            self._pending = self._pending[keep - self._pending_start:]
            self._pending_start = keep

    def image(self) -> np.ndarray:
        """(rows, columns) uint8, ``grid.image_shape``, once every profile has been added."""
        if self._seen != self.grid.shape[0]:
            raise ValueError(f"{self._seen} of {self.grid.shape[0]} profiles added")
        return np.concatenate(self._rows)


def find_circles(image: np.ndarray, *, radius_px: float) -> np.ndarray:
    """Circles of about ``radius_px`` in an 8-bit image: OpenCV's Hough gradient transform after a
    3 x 3 median filter, searching radii 0.6 to 1.3 times ``radius_px``, centres at least 1.5 times
    ``radius_px`` apart. Either polarity (bright on dark or dark on bright) is found.

    image : (h, w) uint8.
    radius_px : the expected radius, pixels.
    Returns (k, 3) float32: x (column), y (row) and radius of each circle, pixels, in the order
    OpenCV ranks them (most votes first); (0, 3) when none is found.
    """
    image = np.asarray(image)
    if image.ndim != 2 or image.dtype != np.uint8:
        raise ValueError(f"image must be a (h, w) uint8 array, got shape {image.shape} and dtype {image.dtype}")
    if not radius_px > 0:
        raise ValueError(f"radius_px must be positive, got {radius_px}")
    blurred = cv2.medianBlur(image, 3)
    circles = cv2.HoughCircles(blurred, cv2.HOUGH_GRADIENT, dp=1, minDist=1.5 * radius_px, param1=100, param2=12,
                               minRadius=max(2, int(0.6 * radius_px)), maxRadius=int(np.ceil(1.3 * radius_px)))
    return np.zeros((0, 3), np.float32) if circles is None else circles[0]
