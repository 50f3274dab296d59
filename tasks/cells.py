"""Points on a grid of cells: the first point of each cell (thinning), and where a point may lie
within a reach of a set of points (which cells to search before asking a k-d tree)."""

from __future__ import annotations

import numpy as np

__all__ = ["first_in_each_cell", "grid_thinning_steps", "ReachGrid"]


def grid_thinning_steps(cell_mm: float, grid_pitch_mm) -> tuple[int, int]:
    """Every how many profiles and columns a grid pass (``grid_pitch_mm``: its spacing between
    profiles and between columns, mm) is thinned to for cells of ``cell_mm``: k per axis as large
    as keeps its points at most a third of a cell apart, about nine to a cell."""
    return tuple(max(1, int(cell_mm / (3 * p))) for p in grid_pitch_mm)  # type: ignore[return-value]


def first_in_each_cell(cells: np.ndarray) -> np.ndarray:
    """The index of the first row of ``cells`` ((n, 3) int64 cell indices) in each distinct cell,
    ascending: ``np.sort(np.unique(cells, axis=0, return_index=True)[1])``, from one int64 key per
    cell (several times quicker than comparing rows) where the cells' span allows it."""
    if len(cells) == 0:
        return np.zeros(0, np.intp)
    low = cells.min(axis=0)
    span = cells.max(axis=0) - low + 1
    if float(span[0]) * float(span[1]) * float(span[2]) >= 2.0 ** 62:
        return np.sort(np.unique(cells, axis=0, return_index=True)[1])
    key = ((cells[:, 0] - low[0]) * span[1] + (cells[:, 1] - low[1])) * span[2] + (cells[:, 2] - low[2])
    return np.sort(np.unique(key, return_index=True)[1])


class ReachGrid:
    """Where a point may have one of ``points_mm`` ((n >= 1, 3)) within ``reach_mm``: the cells (at
    least ``reach_mm`` wide) that hold one of them, and their 26 neighbours (a point within reach
    of another lies in a cell at most one away from that one's), as a boolean grid over the
    points' box of at most about ``max_cells`` cells. ``may_reach`` is False only where none can
    be within reach: a search asked only where it is True answers the same."""

    def __init__(self, points_mm: np.ndarray, reach_mm: float, max_cells: int = 1 << 24):
        self.reach_mm = reach_mm
        # a hair wider than the reach, so that rounding never puts a point within reach two cells away
        self.cell_mm = reach_mm * (1 + 1e-6)
        span = points_mm.max(axis=0) - points_mm.min(axis=0)
        while np.prod(np.floor(span / self.cell_mm) + 3) > max_cells:
            self.cell_mm *= 2
        self.low = points_mm.min(axis=0) - self.cell_mm
        cells = np.floor((points_mm - self.low) / self.cell_mm).astype(np.int64)
        grid = np.zeros(tuple(cells.max(axis=0) + 2), bool)
        grid[tuple(cells.T)] = True
        for axis in range(3):  # grown by one cell along each axis in turn: the 27-cell neighbourhood
            lower, upper = [slice(None)] * 3, [slice(None)] * 3
            lower[axis], upper[axis] = slice(None, -1), slice(1, None)
            grown = grid.copy()
            grown[tuple(lower)] |= grid[tuple(upper)]
            grown[tuple(upper)] |= grid[tuple(lower)]
            grid = grown
        self.grid = grid

    def may_reach(self, points: np.ndarray) -> np.ndarray:
        """(m,) bool: False where none of the grid's points can lie within reach of the point (a
        point that is not finite included)."""
        cells = np.floor((points - self.low) / self.cell_mm)
        inside = np.all((cells >= 0) & (cells < self.grid.shape), axis=1)
        out = np.zeros(len(points), bool)
        out[inside] = self.grid[tuple(cells[inside].astype(np.int64).T)]
        return out
