"""stages.common.rows: distinct integer rows."""

from __future__ import annotations

import numpy as np
import pytest

from stages.common.errors import BlunfError
from stages.common.rows import distinct, distinct_mm, unique_rows


@pytest.mark.parametrize("high", [5, 2**40])
def test_unique_rows_agrees_with_numpys_unique_over_rows(high):
    # 2**40 in three columns overflows the packed key: numpy's own path, the same answer
    keys = np.random.default_rng(0).integers(-high, high, (5000, 3))
    keys[100:200] = keys[:100]  # repeats, whose first occurrence is the earlier copy
    rows, first, inv = unique_rows(keys)
    want_rows, want_first, want_inv = np.unique(
        keys, axis=0, return_index=True, return_inverse=True
    )
    np.testing.assert_array_equal(rows, want_rows)
    np.testing.assert_array_equal(first, want_first)
    np.testing.assert_array_equal(inv, want_inv.reshape(-1))
    np.testing.assert_array_equal(rows[inv], keys)
    assert unique_rows(np.zeros((0, 3), np.int64))[0].shape == (0, 3)
    with pytest.raises(BlunfError, match="integer rows"):
        unique_rows(np.zeros((4, 3)))


def test_distinct_is_np_unique_by_one_sort() -> None:
    rng = np.random.default_rng(3)
    a = rng.integers(-(10**12), 10**12, 50_000)
    a = np.concatenate([a, a[:20_000], [7, 7, -3]])
    assert np.array_equal(distinct(a), np.unique(a))
    assert distinct(np.zeros(0, np.int64)).shape == (0,)
    # plan points rounded to the millimetre: the same rows, order and values as numpy's way
    xy = rng.uniform(-4.0, 9.0, size=(40_000, 2))
    xy = np.concatenate([xy, xy[:10_000] + 1e-5, [[-0.0004, 0.0004]]])  # repeats at 1 mm
    want = np.unique(np.round(xy, 3), axis=0)
    got = distinct_mm(xy)
    assert got.shape == want.shape and np.abs(got - want).max() < 1e-12
    assert distinct_mm(np.zeros((0, 2))).shape == (0, 2)
