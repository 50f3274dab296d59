"""``tasks.arrays``: ``distinct`` the array ``np.unique`` returns, whatever the kind and shape;
``row_medians`` the array ``np.median(axis=1)`` returns."""

from __future__ import annotations

import numpy as np
import pytest

from tasks.arrays import distinct, row_medians

_RNG = np.random.default_rng(7)


@pytest.mark.parametrize("values", [
    _RNG.integers(-5, 5, (7, 3)),  # 2-D: flattened, negative values
    np.zeros(0, np.int64), np.array([3]), np.array([2, 2, 2], np.int32),
    _RNG.integers(0, 2, 50).astype(bool),
    _RNG.integers(0, 1 << 40, 1000).astype(np.uint64),
    [3, 1, 3],  # a list
    np.array([1.0, np.nan, np.nan, 2.0, 1.0]),  # floats keep np.unique's rule: one NaN
], ids=["2d", "empty", "one", "all-equal", "bool", "uint64", "list", "float-nan"])
def test_the_same_array_as_np_unique(values):
    got, expected = distinct(values), np.unique(values)
    assert got.dtype == expected.dtype and np.array_equal(got, expected, equal_nan=True)


def test_many_distinct_keys_are_sorted_and_unique():
    keys = _RNG.integers(0, 1 << 40, 200_000)
    got = distinct(np.concatenate([keys, keys[:1000]]))
    assert np.all(np.diff(got) > 0) and set(got.tolist()) == set(keys.tolist())


@pytest.mark.parametrize("shape", [(1, 1), (4, 2), (3, 7), (300, 7500), (300, 7501)])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_row_medians_the_same_array_as_np_median(shape, dtype):
    values = _RNG.normal(size=shape).astype(dtype)
    ties = np.round(values * 2) / 2  # equal middle values
    for a in (values, ties):
        expected = np.median(a, axis=1)
        got = row_medians(a)
        assert got.dtype == expected.dtype and np.array_equal(got, expected)
        copy = a.copy()
        assert np.array_equal(row_medians(copy, overwrite=True), expected)
    assert np.array_equal(row_medians(values), np.median(values, axis=1))  # values left as they were


@pytest.mark.parametrize("bad", [np.zeros(5), np.zeros((3, 0)), np.zeros((2, 2), np.int64)], ids=["1d", "empty-rows", "int"])
def test_row_medians_refuses_what_it_cannot_answer(bad):
    with pytest.raises(ValueError, match="row_medians takes a"):
        row_medians(bad)
