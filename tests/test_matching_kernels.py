"""The compiled helpers of RoCo's matching against the numpy calls they replace.

Indices, pairs and assignments compare exactly; float results (distances, placed poses,
features, scores) to rounding (``assert_equal_to_rounding``: numpy's exp / sin / cos are
CPU-specific SIMD versions on AVX-512 machines, an ulp off libm's that numba calls)."""

import numpy as np
import pytest
from conftest import assert_equal_to_rounding, kuhn_munkres_matches
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from roco_env.policies.hypothesis_kernels import close_pairs
from roco_env.policies.pose_kernels import compact_pairs, max_weight_assignment


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
    from roco_env.policies.pose_kernels import gated_pairs

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
        assert_equal_to_rounding(d, dis[expected_p, expected_q])
        nearest = dis.argmin(axis=1)
        within = dis.min(axis=1) <= tau2
        np.testing.assert_array_equal(leaves, np.nonzero(within)[0])
        np.testing.assert_array_equal(partner, nearest[within])


def test_placed_landmarks_are_se2_compose_and_pose_features():
    from roco_env.geometry import se2_compose
    from roco_env.policies.matching import pose_features
    from roco_env.policies.pose_kernels import placed_landmarks

    rng = np.random.default_rng(8)
    for _ in range(20):
        own = np.column_stack([rng.uniform(-60, 60, (50, 2)), rng.uniform(-np.pi, np.pi, 50)])
        own[:5, 2] = [np.pi, -np.pi, np.pi / 2, 0.0, -0.0]  # wrap edges
        pose = np.array([*rng.normal(0, 20, 2), rng.choice([np.pi, -np.pi, rng.normal()])])
        boxes = np.sort(rng.choice(50, int(rng.integers(0, 50)), replace=False))
        poses, features = placed_landmarks(pose, own, boxes)
        expected = se2_compose(pose, own[boxes])
        assert_equal_to_rounding(poses, expected)
        for got_row, expected_row in zip(features, pose_features(expected), strict=True):
            assert_equal_to_rounding(got_row, expected_row)  # each at its own magnitude


def numpy_committed_map(pose, own, covariance, match_land, match_box, agent, land_poses,
                        land_features, land_covariance, obs_agent, obs_box, obs_land):
    """The array path of RoCo's commit that ``committed_map`` replaces."""
    from roco_env.geometry import se2_compose
    from roco_env.policies.matching import pose_features

    unmatched = np.ones(own.shape[0], dtype=bool)
    unmatched[match_box] = False
    new_boxes = np.nonzero(unmatched)[0]
    new_ids = np.arange(land_poses.shape[0], land_poses.shape[0] + new_boxes.size)
    new_poses = se2_compose(pose, own[new_boxes])
    return (
        np.concatenate([land_poses, new_poses]),
        np.concatenate([land_features, pose_features(new_poses)], axis=1),
        np.concatenate([land_covariance, covariance[new_boxes]]),
        np.concatenate([obs_agent, np.full(own.shape[0], agent, dtype=np.int64)]),
        np.concatenate([obs_box, match_box, new_boxes]),
        np.concatenate([obs_land, match_land, new_ids]),
    )


def test_committed_map_is_the_array_path():
    from roco_env.policies.matching import pose_features
    from roco_env.policies.pose_kernels import (
        AgentBoxes,
        LandmarkMap,
        Observations,
        committed_map,
    )

    rng = np.random.default_rng(31)
    for _ in range(30):
        n_land, n_own, n_obs = (int(v) for v in rng.integers(0, 40, 3))
        land = np.column_stack([rng.uniform(-50, 50, (n_land, 2)), rng.uniform(-3, 3, n_land)])
        own = np.column_stack([rng.uniform(-50, 50, (n_own, 2)), rng.uniform(-3, 3, n_own)])
        covariance = rng.normal(size=(n_own, 3, 3))
        n_match = int(rng.integers(0, min(n_land, n_own) + 1))
        match_land = np.sort(rng.choice(n_land, n_match, replace=False))
        match_box = rng.choice(n_own, n_match, replace=False)  # any order, as the assignment's
        args = (
            np.array([*rng.normal(0, 10, 2), rng.uniform(-np.pi, np.pi)]), own, covariance,
            match_land, match_box, int(rng.integers(1, 9)), land, pose_features(land),
            rng.normal(size=(n_land, 3, 3)), rng.integers(0, 9, n_obs), rng.integers(0, 40, n_obs),
            rng.integers(0, max(n_land, 1), n_obs),
        )
        (pose, own, covariance, match_land, match_box, agent, land, features, land_covariance,
         obs_agent, obs_box, obs_land) = args
        boxes = AgentBoxes(own, np.zeros_like(covariance), covariance, pose_features(own),
                           np.zeros(3))
        landmarks, observations = committed_map(
            pose, match_land, match_box, boxes, agent,
            LandmarkMap(land, features, land_covariance), Observations(obs_agent, obs_box, obs_land))
        landmarks, observations = LandmarkMap(*landmarks), Observations(*observations)
        want_poses, want_features, *want_rest = numpy_committed_map(*args)
        assert landmarks.poses.dtype == want_poses.dtype == landmarks.features.dtype
        for got_column, expected_column in zip(landmarks.poses.T, want_poses.T, strict=True):
            assert_equal_to_rounding(got_column, expected_column)  # x, y, yaw each at its own
        for got_row, expected_row in zip(landmarks.features, want_features, strict=True):
            assert_equal_to_rounding(got_row, expected_row)  # magnitude (cos, sin: to 1e-12)
        for got, expected in zip((landmarks.covariance, *observations), want_rest, strict=True):
            assert got.dtype == expected.dtype
            np.testing.assert_array_equal(got, expected)  # covariances copied, observation ids


def _edge_similarity_reference(land, box, cand_p, cand_q, leaves, partner):
    """S_edge (C,) of the candidate pairs from the pose features (5, L) / (5, K) by the
    dense bilinear form (every leaf a star's leaf, no radius): the (C, 11) candidate and
    (11, H) leaf factors of ||T_pm T_qn^{-1} - I||_F^2 (matching's module docstring) as
    numpy products, the leaf of p itself and the pairs whose q is the leaf's partner left
    out of the mean."""
    px, py, p2, pc, ps = land[:, cand_p]
    qx, qy, q2, qc, qs = box[:, cand_q]
    cand = np.stack([np.ones_like(px), pc * qc + ps * qs, ps * qc - pc * qs, px, py, p2,
                     qx, qy, q2, px * qx + py * qy, py * qx - px * qy], axis=1)
    mx, my, m2, mc, ms = land[:, leaves]
    nx, ny, n2, nc, ns = box[:, partner]
    cu, su = mc * nc + ms * ns, ms * nc - mc * ns
    rot_n_x, rot_n_y = cu * nx - su * ny, su * nx + cu * ny
    rot_m_x, rot_m_y = mx * cu + my * su, my * cu - mx * su
    leaf = np.stack([4.0 + m2 + n2 - 2.0 * (mx * rot_n_x + my * rot_n_y), -4.0 * cu, -4.0 * su,
                     2.0 * (rot_n_x - mx), 2.0 * (rot_n_y - my), np.ones_like(mx),
                     2.0 * (rot_m_x - nx), 2.0 * (rot_m_y - ny), np.ones_like(mx), -2.0 * cu,
                     -2.0 * su])
    usable = (leaves[None, :] != cand_p[:, None]) & (partner[None, :] != cand_q[:, None])
    norm2 = np.zeros((cand_p.size, leaves.size))
    for i in range(11):  # the compiled loop's order (a matrix product may sum otherwise)
        norm2 += cand[:, i, None] * leaf[None, i, :]
    terms = np.exp(-np.sqrt(np.maximum(norm2, 0.0)))
    return np.where(usable, terms, 0.0).sum(axis=1) / np.maximum(usable.sum(axis=1), 1)


@pytest.mark.parametrize("terms", [(True, True), (True, False), (False, True)])
def test_scored_pairs_match_the_array_path(terms):
    """Gate, S = lam S_dis + S_edge (all boxes leaves; cached S_edge reused) and the
    assignment (its shortcut and Kuhn-Munkres), against gated_pairs + np.exp + the dense
    edge similarity + scipy's assignment."""
    from roco_env.policies.matching import MatchingParams, pose_features
    from roco_env.policies.pose_kernels import empty_match_cache, gated_pairs, scored_pairs

    use_distance, use_edge = terms
    p = MatchingParams(use_distance_similarity=use_distance, use_edge_similarity=use_edge,
                       lam=1.0 if use_distance else 0.0, neighbor_radius=None)
    settings = p.match_settings()
    rng = np.random.default_rng(12)
    cache = empty_match_cache()
    shortcuts = below = 0
    for trial in range(30):
        lands = np.column_stack([rng.uniform(-120, 120, (40, 2)), rng.uniform(-3, 3, 40)])
        own = lands[rng.choice(40, 25, replace=False)] + rng.normal(0, [0.4, 0.4, 0.02], (25, 3))
        centres = np.ascontiguousarray(own[:, :2] + rng.normal(0, 0.2, 2))
        tau2 = 3.0 if trial % 3 else 8.0  # the wide gate gives several candidates per box
        for _ in range(2):  # the second call reuses the cached S_edge
            land, box, score, cache = scored_pairs(
                np.ascontiguousarray(lands[:, :2]), centres, tau2, pose_features(lands),
                pose_features(own), settings, cache)
        ref_p, ref_q, dis, leaves, partner = gated_pairs(np.ascontiguousarray(lands[:, :2]),
                                                         centres, tau2)
        expected = p.lam * np.exp(-dis) if use_distance else np.zeros(ref_p.size)
        if use_edge:
            expected = expected + _edge_similarity_reference(
                pose_features(lands), pose_features(own), ref_p, ref_q, leaves, partner)
        want_land, want_box, want_score = kuhn_munkres_matches(ref_p, ref_q, expected,
                                                               p.similarity_threshold)
        np.testing.assert_array_equal(land, want_land)
        np.testing.assert_array_equal(box, want_box)
        assert_equal_to_rounding(score, want_score)
        single = np.unique(ref_p).size == ref_p.size and np.unique(ref_q).size == ref_q.size
        shortcuts += single
        below += single and bool((expected > 0).all() and (expected < p.similarity_threshold).any())
    assert 0 < shortcuts < 30  # both the shortcut and the full assignment are exercised
    assert below > 0  # and the shortcut's bar on S drops pairs


@pytest.mark.parametrize("ties", [False, True])
def test_max_weight_assignment_is_scipys(ties):
    """scipy's linear_sum_assignment(maximize=True) to the index, on wide, tall and square
    matrices; with ties: few distinct values, zero rows and columns, constant blocks."""
    rng = np.random.default_rng(40 + ties)
    for trial in range(300):
        shape = tuple(int(v) for v in rng.integers(1, 13, 2))
        if ties:
            weights = rng.integers(0, 3, shape).astype(float) * rng.choice([0.5, 1.0])
            weights[rng.random(shape[0]) < 0.2] = 0.0
            if trial % 5 == 0:
                weights[:] = 1.0
        else:
            weights = rng.uniform(0.0, 2.0, shape)
            weights[rng.random(shape) < 0.5] = 0.0  # the matcher's non-candidates
        rows, cols = max_weight_assignment(weights)
        want_rows, want_cols = linear_sum_assignment(weights, maximize=True)
        np.testing.assert_array_equal(rows, want_rows, err_msg=f"{weights}")
        np.testing.assert_array_equal(cols, want_cols, err_msg=f"{weights}")


def test_close_pairs_keep_ties_and_the_radius_edge_of_the_dense_scan():
    """Centres on a lattice (many equal x, distances exactly at the radius) and repeated
    centres: the windowed search gives the dense scan's pairs in row-major order."""
    rng = np.random.default_rng(23)
    lattice = np.stack(np.meshgrid(np.arange(-6.0, 7.0), np.arange(-6.0, 7.0)), -1).reshape(-1, 2)
    for radius in (0.0, 1.0, 2.0, 5.0):
        a = lattice[rng.permutation(lattice.shape[0])[:80]] * 1.5
        b = np.vstack([lattice[rng.permutation(lattice.shape[0])[:90]], lattice[:10]]) * 1.5
        first, second = close_pairs(a, b, radius * 1.5)
        dx = a[:, None, 0] - b[None, :, 0]
        dy = a[:, None, 1] - b[None, :, 1]
        i, j = np.nonzero(np.sqrt(dx * dx + dy * dy) <= radius * 1.5)
        np.testing.assert_array_equal(first, i)
        np.testing.assert_array_equal(second, j)


def test_gated_pairs_keep_ties_and_the_gate_edge_of_the_dense_scan():
    """Lattice centres (equal x, distances exactly at the gate, equidistant boxes) and
    repeated boxes: the windowed scan keeps the dense definition's pairs and nearest boxes
    (the lowest index among equal distances)."""
    from roco_env.policies.pose_kernels import gated_pairs

    rng = np.random.default_rng(24)
    lattice = np.stack(np.meshgrid(np.arange(-6.0, 7.0), np.arange(-6.0, 7.0)), -1).reshape(-1, 2)
    for tau2 in (1.0, 2.0, 3.0):
        land = lattice[rng.permutation(lattice.shape[0])[:70]] * 1.5 + 0.75
        centres = np.vstack([lattice[rng.permutation(lattice.shape[0])[:60]], lattice[:8]]) * 1.5
        dx = land[:, None, 0] - centres[None, :, 0]
        dy = land[:, None, 1] - centres[None, :, 1]
        dis = np.sqrt(dx * dx + dy * dy)
        cand_p, cand_q, d, leaves, partner = gated_pairs(land, centres, tau2 * 1.5)
        expected_p, expected_q = np.nonzero(dis <= tau2 * 1.5)
        np.testing.assert_array_equal(cand_p, expected_p)
        np.testing.assert_array_equal(cand_q, expected_q)
        assert_equal_to_rounding(d, dis[expected_p, expected_q])
        within = dis.min(axis=1) <= tau2 * 1.5
        np.testing.assert_array_equal(leaves, np.nonzero(within)[0])
        np.testing.assert_array_equal(partner, dis.argmin(axis=1)[within])
