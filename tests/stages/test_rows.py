"""stages.common.rows: distinct integer rows."""

from __future__ import annotations

import numpy as np
import pytest

from stages.common.errors import BlunfError
from stages.common.rows import unique_rows


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
