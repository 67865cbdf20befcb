"""The compiled helpers of RoCo's matching against the numpy calls they replace."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from roco_env.policies.matching_kernels import close_pairs, compact_pairs


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


def _numpy_best_gains(ego, collab, pose, p):
    """The array path: k-d tree pairs within the radius where a pair can still gain, chi2
    per pair, np.maximum.at per box."""
    from roco_env.policies.hypotheses import _half_turn, _map, _size_chi2

    mapped = _map(pose, collab.poses)
    slack_t, slack_r = p.pose_slack_t**2, np.deg2rad(p.pose_slack_r_deg) ** 2
    widest = ego.var_t.max(initial=0.0) + collab.var_t.max(initial=0.0) + slack_t
    found = cKDTree(ego.poses[:, :2]).sparse_distance_matrix(
        cKDTree(mapped[:, :2]), float(np.sqrt(p.outlier_chi2 * widest)), output_type="ndarray")
    i, j = found["i"].astype(np.int64), found["j"].astype(np.int64)
    dx, dy = ego.poses[i, 0] - mapped[j, 0], ego.poses[i, 1] - mapped[j, 1]
    dyaw = _half_turn(ego.poses[i, 2] - mapped[j, 2])
    chi2 = (dx * dx + dy * dy) / (ego.var_t[i] + collab.var_t[j] + slack_t)
    chi2 += dyaw * dyaw / (ego.var_r[i] + collab.var_r[j] + slack_r)
    if p.use_size:
        chi2 += _size_chi2(ego, collab, i, j, p)
    gain = p.outlier_chi2 - chi2
    keep = gain > 0
    forward, backward = np.zeros(collab.poses.shape[0]), np.zeros(ego.poses.shape[0])
    np.maximum.at(forward, j[keep], gain[keep])
    np.maximum.at(backward, i[keep], gain[keep])
    return forward, backward


@pytest.mark.parametrize("use_size", [True, False])
def test_best_pair_gains_match_the_numpy_path(use_size):
    from roco_env.policies.hypotheses import EvidenceParams, _best_gains, box_set

    rng = np.random.default_rng(21)
    p = EvidenceParams(use_size=use_size)
    for _ in range(10):
        ego_boxes = np.column_stack([rng.uniform(-30, 30, (40, 2)), rng.normal(size=40),
                                     rng.uniform(1, 5, (40, 3)), rng.uniform(-3, 3, 40)])
        collab_boxes = ego_boxes[rng.choice(40, 25, replace=False)].copy()
        collab_boxes[:, [0, 1, 6]] += rng.normal(size=(25, 3)) * [0.3, 0.3, 0.05]
        sets = []
        for boxes in (ego_boxes, collab_boxes):
            poses = boxes[:, [0, 1, 6]]
            sigma = rng.uniform(0.1, 0.6, (boxes.shape[0], 3))
            info = np.zeros((boxes.shape[0], 3, 3))
            info[:, [0, 1, 2], [0, 1, 2]] = sigma**-2
            sets.append(box_set(boxes, poses, info))
        pose = rng.normal(size=3) * [0.3, 0.3, 0.02]
        forward, backward = _best_gains(sets[0], sets[1], pose, p)
        expected = _numpy_best_gains(sets[0], sets[1], pose, p)
        np.testing.assert_array_equal(forward, expected[0])
        np.testing.assert_array_equal(backward, expected[1])
        assert np.count_nonzero(forward) > 5  # the case exercises gaining pairs


def test_close_pairs_are_the_k_d_tree_pairs_in_row_major_order():
    rng = np.random.default_rng(22)
    for radius in (0.5, 3.0, 12.0):
        a, b = rng.uniform(-20, 20, (60, 2)), rng.uniform(-20, 20, (45, 2))
        first, second = close_pairs(a, b, radius)
        found = cKDTree(a).sparse_distance_matrix(cKDTree(b), radius, output_type="ndarray")
        expected = sorted(zip(found["i"].tolist(), found["j"].tolist(), strict=True))
        assert list(zip(first.tolist(), second.tolist(), strict=True)) == expected
    empty = close_pairs(np.zeros((0, 2)), b, 3.0)
    assert empty[0].size == empty[1].size == 0


def test_gated_pairs_match_the_dense_definition():
    from roco_env.policies.matching_kernels import gated_pairs

    rng = np.random.default_rng(23)
    for tau2 in (1.0, 3.0, 6.0):
        land, centres = rng.uniform(-25, 25, (70, 2)), rng.uniform(-25, 25, (50, 2))
        dx = land[:, None, 0] - centres[None, :, 0]
        dy = land[:, None, 1] - centres[None, :, 1]
        dis = np.sqrt(dx * dx + dy * dy)
        cand_p, cand_q, d, leaves, partner = gated_pairs(land, centres, tau2)
        expected_p, expected_q = np.nonzero(dis <= tau2)
        np.testing.assert_array_equal(cand_p, expected_p)
        np.testing.assert_array_equal(cand_q, expected_q)
        np.testing.assert_array_equal(d, dis[expected_p, expected_q])
        nearest = dis.argmin(axis=1)
        within = dis.min(axis=1) <= tau2
        np.testing.assert_array_equal(leaves, np.nonzero(within)[0])
        np.testing.assert_array_equal(partner, nearest[within])
