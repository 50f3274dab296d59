"""Points on a grid of cells (tasks.cells) against numpy's own row-wise answer."""

from __future__ import annotations

import numpy as np
import pytest

from tasks.cells import first_in_each_cell


@pytest.mark.parametrize("scale", [1, 2 ** 40], ids=["one-key", "rows-too-wide-for-one-key"])
def test_the_first_point_of_each_cell_is_numpys(scale):
    rng = np.random.default_rng(4)
    cells = rng.integers(-20, 20, (5000, 3)) * np.array([1, 1, scale])
    expected = np.sort(np.unique(cells, axis=0, return_index=True)[1])
    got = first_in_each_cell(cells)
    assert 0 < len(got) < len(cells) and np.array_equal(got, expected)
    assert len(first_in_each_cell(np.zeros((0, 3), np.int64))) == 0
