"""The compiled helpers of RoCo's matching against the numpy calls they replace."""

import numpy as np

from roco_env.policies.matching_kernels import compact_pairs


def test_compact_pairs_is_np_unique_with_inverse():
    rng = np.random.default_rng(3)
    for trial in range(40):
        n = int(rng.integers(1, 30))
        cand_p = np.sort(rng.integers(0, 12, n))
        cand_q = rng.integers(0, 9, n) if trial % 2 else rng.permutation(40)[:n]
        rows, row_idx, cols, col_idx, single = compact_pairs(cand_p, cand_q)
        expected_rows, expected_row_idx = np.unique(cand_p, return_inverse=True)
        expected_cols, expected_col_idx = np.unique(cand_q, return_inverse=True)
        np.testing.assert_array_equal(rows, expected_rows)
        np.testing.assert_array_equal(row_idx, expected_row_idx)
        np.testing.assert_array_equal(cols, expected_cols)
        np.testing.assert_array_equal(col_idx, expected_col_idx)
        assert single == (np.bincount(cand_p).max() == 1 and np.bincount(cand_q).max() == 1)


def test_compact_pairs_of_no_pairs_is_empty():
    empty = np.zeros(0, dtype=np.int64)
    rows, row_idx, cols, col_idx, single = compact_pairs(empty, empty)
    assert rows.size == row_idx.size == cols.size == col_idx.size == 0 and single
