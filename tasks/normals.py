"""Normals on an organized pass: a plane fitted to each point's grid neighbours, turned toward the
sensor that saw the point.

The paper fits each normal to the point's 100 nearest neighbours (a k-d tree over the merged
cloud). A pass is an organized grid, so the neighbours are the points of a window of profiles x
columns around the point: no tree, linear work, and a pass can be processed in blocks of profiles
(each with ``window_rows`` halo rows) with the same result as the whole pass. The normals then
travel through the box-grid merge (averaged per cell), so the merged cloud needs no neighbour
search at all.

The plane is the eigenvector of the smallest eigenvalue of the window's covariance (closed form
for a 3 x 3 symmetric matrix). Where the window holds too few points, or they lie on a line (a
single profile's edge), the normal is the direction to the sensor: what Poisson needs there is an
outward direction, and the sensor is outside.

Compiled with Numba; each point's normal depends on its window alone and sums run in a fixed
order, so the same bytes come out for any blocking and thread count.
"""

from __future__ import annotations

from tasks.kernels import numba
import numpy as np

__all__ = ["grid_normals", "normal_window"]


def normal_window(window_mm: float, pitch_mm: tuple[float, float]) -> tuple[int, int]:
    """Half-widths (rows, columns) of a window about ``window_mm`` on a side on a grid of pitch
    (between profiles, between columns) mm; at least one row and one column each way."""
    row_mm, col_mm = pitch_mm
    if not (window_mm > 0 and row_mm > 0 and col_mm > 0):
        raise ValueError(f"window_mm and the grid pitch must be positive, got {window_mm}, {pitch_mm}")
    return max(1, int(round(window_mm / 2 / row_mm))), max(1, int(round(window_mm / 2 / col_mm)))


@numba.njit(cache=True)
def _smallest_eigenvector(a00, a01, a02, a11, a12, a22):
    """Unit eigenvector of the smallest eigenvalue of a symmetric 3x3 matrix; zeros when the two
    smallest eigenvalues are (nearly) equal, i.e. the points lie on a line or a point."""
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    p2 = b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * p1
    if p2 <= 0.0:
        return 0.0, 0.0, 0.0
    p = np.sqrt(p2 / 6.0)
    det = (b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02))
    r = det / (2.0 * p * p * p)
    r = min(max(r, -1.0), 1.0)
    phi = np.arccos(r) / 3.0
    large = q + 2.0 * p * np.cos(phi)
    small = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    middle = 3.0 * q - large - small
    if middle - small <= 1e-9 * max(large, 1e-300):
        return 0.0, 0.0, 0.0
    # rows of (A - small I): the eigenvector is orthogonal to them; the largest cross product wins
    r0x, r0y, r0z = a00 - small, a01, a02
    r1x, r1y, r1z = a01, a11 - small, a12
    r2x, r2y, r2z = a02, a12, a22 - small
    c0x, c0y, c0z = r0y * r1z - r0z * r1y, r0z * r1x - r0x * r1z, r0x * r1y - r0y * r1x
    c1x, c1y, c1z = r0y * r2z - r0z * r2y, r0z * r2x - r0x * r2z, r0x * r2y - r0y * r2x
    c2x, c2y, c2z = r1y * r2z - r1z * r2y, r1z * r2x - r1x * r2z, r1x * r2y - r1y * r2x
    n0 = c0x * c0x + c0y * c0y + c0z * c0z
    n1 = c1x * c1x + c1y * c1y + c1z * c1z
    n2 = c2x * c2x + c2y * c2y + c2z * c2z
    if n0 >= n1 and n0 >= n2:
        x, y, z, n = c0x, c0y, c0z, n0
    elif n1 >= n2:
        x, y, z, n = c1x, c1y, c1z, n1
    else:
        x, y, z, n = c2x, c2y, c2z, n2
    if n <= 0.0:
        return 0.0, 0.0, 0.0
    s = 1.0 / np.sqrt(n)
    return x * s, y * s, z * s


@numba.njit(parallel=True, cache=True)
def _column_sums(points, reference, r_lo, r_hi, wc, sums):
    # sliding window along each row (add the column entering, remove the one leaving), on
    # coordinates relative to ``reference``: each row's sums depend on that row alone
    w = points.shape[1]
    ox, oy, oz = reference[0], reference[1], reference[2]
    for r in numba.prange(r_lo, r_hi):
        acc = np.zeros(10)
        for c in range(-wc, w + wc):
            enter, leave = c + wc, c - wc - 1
            if enter < w:
                x, y, z = points[r, enter, 0] - ox, points[r, enter, 1] - oy, points[r, enter, 2] - oz
                if np.isfinite(x) and np.isfinite(y) and np.isfinite(z):
                    acc[0] += 1.0
                    acc[1] += x
                    acc[2] += y
                    acc[3] += z
                    acc[4] += x * x
                    acc[5] += x * y
                    acc[6] += x * z
                    acc[7] += y * y
                    acc[8] += y * z
                    acc[9] += z * z
            if leave >= 0:
                x, y, z = points[r, leave, 0] - ox, points[r, leave, 1] - oy, points[r, leave, 2] - oz
                if np.isfinite(x) and np.isfinite(y) and np.isfinite(z):
                    acc[0] -= 1.0
                    acc[1] -= x
                    acc[2] -= y
                    acc[3] -= z
                    acc[4] -= x * x
                    acc[5] -= x * y
                    acc[6] -= x * z
                    acc[7] -= y * y
                    acc[8] -= y * z
                    acc[9] -= z * z
            if 0 <= c < w:
                for m in range(10):
                    sums[r - r_lo, c, m] = acc[m]


@numba.njit(parallel=True, cache=True)
def _normal_kernel(points, origins, reference, row0, row1, wr, min_points, sums, r_lo, out):
    h, w = points.shape[0], points.shape[1]
    for i in numba.prange(row0, row1):
        for j in range(w):
            px, py, pz = points[i, j, 0], points[i, j, 1], points[i, j, 2]
            if not (np.isfinite(px) and np.isfinite(py) and np.isfinite(pz)):
                out[i - row0, j, 0] = np.nan
                out[i - row0, j, 1] = np.nan
                out[i - row0, j, 2] = np.nan
                continue
            cnt = ax = ay = az = axx = axy = axz = ayy = ayz = azz = 0.0
            for r in range(max(i - wr, 0), min(i + wr + 1, h)):
                row = sums[r - r_lo, j]
                cnt += row[0]
                ax += row[1]
                ay += row[2]
                az += row[3]
                axx += row[4]
                axy += row[5]
                axz += row[6]
                ayy += row[7]
                ayz += row[8]
                azz += row[9]
            nx, ny, nz = 0.0, 0.0, 0.0
            if cnt >= min_points - 0.5:  # the count is a float sum of ones: exact
                mx, my, mz = ax / cnt, ay / cnt, az / cnt
                nx, ny, nz = _smallest_eigenvector(axx / cnt - mx * mx, axy / cnt - mx * my, axz / cnt - mx * mz,
                                                   ayy / cnt - my * my, ayz / cnt - my * mz, azz / cnt - mz * mz)
            sx, sy, sz = origins[i, 0] - px, origins[i, 1] - py, origins[i, 2] - pz
            if nx == 0.0 and ny == 0.0 and nz == 0.0:
                s = 1.0 / np.sqrt(sx * sx + sy * sy + sz * sz)
                nx, ny, nz = sx * s, sy * s, sz * s
            elif nx * sx + ny * sy + nz * sz < 0.0:
                nx, ny, nz = -nx, -ny, -nz
            out[i - row0, j, 0] = nx
            out[i - row0, j, 1] = ny
            out[i - row0, j, 2] = nz


def grid_normals(points_mm: np.ndarray, sensor_origins_mm: np.ndarray, *, window_rows: int, window_cols: int,
                 min_points: int, reference_mm: np.ndarray, rows: slice | None = None) -> np.ndarray:
    """Unit normals of an organized cloud, each toward the sensor that saw its point.

    points_mm : (profiles, columns, 3) float, mm; NaN marks a missing (or removed) point. For a
        block of a pass, its rows with ``window_rows`` halo rows on each side.
    sensor_origins_mm : (profiles, 3) float, mm, the sensor's position at each profile.
    window_rows, window_cols : half-widths of the window of grid neighbours, >= 1 (``normal_window``).
    min_points : fewest points (the point included) in the window for a fitted plane, >= 3.
    reference_mm : (3,) a point near the pass; sums are taken relative to it (precision). Every
        block of a pass must use the same one for the blocks to give the whole pass's bytes.
    rows : the rows to compute (default all).
    Returns (len(rows), columns, 3) float64: unit vectors with dot(normal, sensor - point) > 0, NaN
    where the point is missing.
    """
    points = np.ascontiguousarray(points_mm, dtype=np.float64)
    if points.ndim != 3 or points.shape[2] != 3:
        raise ValueError(f"points_mm must have shape (profiles, columns, 3), got {points.shape}")
    origins = np.ascontiguousarray(sensor_origins_mm, dtype=np.float64)
    if origins.shape != (points.shape[0], 3) or not np.isfinite(origins).all():
        raise ValueError(f"sensor_origins_mm must be a finite ({points.shape[0]}, 3) array, got {origins.shape}")
    if window_rows < 1 or window_cols < 1:
        raise ValueError(f"window half-widths must be >= 1, got {window_rows}, {window_cols}")
    if min_points < 3:
        raise ValueError(f"min_points must be >= 3 (a plane needs three points), got {min_points}")
    reference = np.asarray(reference_mm, dtype=np.float64)
    if reference.shape != (3,) or not np.isfinite(reference).all():
        raise ValueError(f"reference_mm must be a finite (3,) point, got {reference}")
    h = points.shape[0]
    start, stop, _ = (rows or slice(None)).indices(h)
    out = np.empty((max(stop - start, 0), points.shape[1], 3))
    if stop <= start:
        return out
    r_lo, r_hi = max(start - window_rows, 0), min(stop + window_rows, h)
    sums = np.empty((r_hi - r_lo, points.shape[1], 10))
    _column_sums(points, reference, r_lo, r_hi, int(window_cols), sums)
    _normal_kernel(points, origins, reference, start, stop, int(window_rows), float(min_points), sums, r_lo, out)
    return out
