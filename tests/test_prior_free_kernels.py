"""The compiled loops of the prior-free aligners against the numpy formulations they
replaced (roco_env/policies/prior_free_kernels.py), on random boxes and poses.

Pairs, counts and kept hypotheses compare exactly; distances and poses to rounding
(``assert_equal_to_rounding``: numpy's sin / cos are CPU-specific SIMD versions on
AVX-512 machines, an ulp off libm's that numba calls)."""

import numpy as np
import pytest
from conftest import assert_equal_to_rounding
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from roco_env.policies.prior_free import _associate, axial_difference, fit_se2
from roco_env.policies.prior_free_kernels import (
    Gates,
    PairInvariants,
    Placement,
    inlier_counts,
    matching_pairs,
)

YAW_GATE = np.deg2rad(10.0)


def random_boxes(rng, count, extent=40.0):
    """(count, 3) box poses: centres in a square, any heading."""
    return np.column_stack([rng.uniform(-extent, extent, (count, 2)),
                            rng.uniform(-np.pi, np.pi, count)])


def numpy_associate(pose, ego, own, gate, yaw_gate):
    """The dense numpy association: every pair within the gates, Hungarian on conflicts."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    x = pose[0] + c * own[:, 0] - s * own[:, 1]
    y = pose[1] + s * own[:, 0] + c * own[:, 1]
    dx, dy = ego[:, None, 0] - x[None, :], ego[:, None, 1] - y[None, :]
    dist2 = dx * dx + dy * dy
    ok = dist2 <= gate * gate
    if yaw_gate is not None:
        ok &= axial_difference(ego[:, None, 2], own[None, :, 2] + pose[2]) <= yaw_gate
    rows, cols = np.nonzero(ok)
    if np.all(rows[1:] != rows[:-1]) and (cols.size == 0 or np.bincount(cols).max() == 1):
        return rows, cols, np.sqrt(dist2[rows, cols])
    r, c = linear_sum_assignment(np.where(ok, np.sqrt(dist2), 1e6))
    keep = ok[r, c]
    return r[keep], c[keep], np.sqrt(dist2[r[keep], c[keep]])


@pytest.mark.parametrize("seed", range(20))
def test_association_matches_the_dense_numpy_path(seed):
    rng = np.random.default_rng(seed)
    ego = random_boxes(rng, int(rng.integers(1, 60)))
    # Collaborator boxes: some of the ego's seen from a pose, jittered, plus clutter;
    # a 3 m gate on boxes ~5 m apart leaves both one-to-one and competing cases.
    pose = np.array([*rng.uniform(-5, 5, 2), rng.uniform(-np.pi, np.pi)])
    c, s = np.cos(-pose[2]), np.sin(-pose[2])
    shifted = ego[: max(1, ego.shape[0] // 2), :2] - pose[:2]
    local = np.column_stack([c * shifted[:, 0] - s * shifted[:, 1],
                             s * shifted[:, 0] + c * shifted[:, 1],
                             ego[: shifted.shape[0], 2] - pose[2]])
    own = np.vstack([local + rng.normal(0, 0.5, local.shape), random_boxes(rng, 10)])
    for gate, yaw_gate in [(3.0, YAW_GATE), (1.5, YAW_GATE), (6.0, None)]:
        (rows, cols, dist), (want_rows, want_cols, want_dist) = (
            _associate(pose, ego, own, gate, yaw_gate),
            numpy_associate(pose, ego, own, gate, yaw_gate))
        np.testing.assert_array_equal(rows, want_rows)
        np.testing.assert_array_equal(cols, want_cols)
        assert_equal_to_rounding(dist, want_dist)


def test_association_resolves_competition_by_total_distance():
    ego = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    own = np.array([[0.9, 0.0, 0.0], [2.1, 0.0, 0.0]])  # own 0 is within 3 m of both
    rows, cols, dist = _associate(np.zeros(3), ego, own, 3.0, YAW_GATE)
    assert rows.tolist() == [0, 1] and cols.tolist() == [0, 1]
    np.testing.assert_allclose(dist, [0.9, 0.1])


def numpy_inlier_counts(poses, ego, own, gate, yaw_gate):
    """Per hypothesis, own boxes whose nearest ego box (k-d tree) is within the gates."""
    c, s = np.cos(poses[:, 2])[:, None], np.sin(poses[:, 2])[:, None]
    x = poses[:, 0:1] + c * own[None, :, 0] - s * own[None, :, 1]
    y = poses[:, 1:2] + s * own[None, :, 0] + c * own[None, :, 1]
    dist, nearest = cKDTree(ego[:, :2]).query(np.column_stack([x.ravel(), y.ravel()]),
                                              distance_upper_bound=gate)
    found = np.isfinite(dist)
    yaw = (poses[:, 2:3] + own[None, :, 2]).ravel()
    ok = found.copy()
    ok[found] = axial_difference(ego[nearest[found], 2], yaw[found]) <= yaw_gate
    return ok.reshape(poses.shape[0], own.shape[0]).sum(axis=1)


@pytest.mark.parametrize("seed", range(10))
def test_inlier_counts_match_the_kd_tree_path(seed):
    rng = np.random.default_rng(seed)
    ego = random_boxes(rng, 60)
    own = ego[rng.choice(60, 24, replace=False)] + rng.normal(0, [0.5, 0.5, 0.1], (24, 3))
    poses = np.vstack([np.zeros(3), np.column_stack(
        [rng.normal(0, 2, (199, 2)), rng.normal(0, 0.05, 199)])])
    placement = Placement(poses[:, 0].copy(), poses[:, 1].copy(), np.cos(poses[:, 2]),
                          np.sin(poses[:, 2]), poses[:, 2].copy())
    got = inlier_counts(placement, ego, own, Gates(1.5, YAW_GATE))
    want = numpy_inlier_counts(poses, ego, own, 1.5, YAW_GATE)
    np.testing.assert_array_equal(got, want)
    assert want.max() > 10 > want.min()  # the poses span hits and misses


@pytest.mark.parametrize("yaw_tol", [np.deg2rad(10.0), -1.0])
def test_matching_pairs_match_the_searchsorted_path(yaw_tol):
    rng = np.random.default_rng(3)
    elen, clen = rng.uniform(4, 80, 500), rng.uniform(4, 80, 200)
    erel, ebear, crel, cbear = (rng.uniform(-np.pi, np.pi, n) for n in (500, 500, 200, 200))
    order = np.argsort(elen)
    got = matching_pairs(PairInvariants(elen[order], erel[order], ebear[order]), order,
                         PairInvariants(clen, crel, cbear), Gates(0.6, yaw_tol))
    lo = np.searchsorted(elen[order], clen - 0.6, "left")
    hi = np.searchsorted(elen[order], clen + 0.6, "right")
    counts = hi - lo
    own_idx = np.repeat(np.arange(clen.size), counts)
    ego_idx = order[np.arange(own_idx.size) + np.repeat(lo - np.cumsum(counts) + counts, counts)]
    if yaw_tol >= 0:
        ok = (axial_difference(erel[ego_idx], crel[own_idx]) <= yaw_tol) & (
            axial_difference(ebear[ego_idx], cbear[own_idx]) <= yaw_tol)
        ego_idx, own_idx = ego_idx[ok], own_idx[ok]
    assert ego_idx.size >= 10
    np.testing.assert_array_equal(got[0], ego_idx)
    np.testing.assert_array_equal(got[1], own_idx)


@pytest.mark.parametrize("seed", range(5))
def test_fit_se2_matches_the_numpy_closed_form(seed):
    rng = np.random.default_rng(seed)
    src = rng.uniform(-30, 30, (12, 2))
    pose = np.array([3.0, -2.0, 0.7])
    c, s = np.cos(pose[2]), np.sin(pose[2])
    dst = src @ np.array([[c, s], [-s, c]]) + pose[:2] + rng.normal(0, 0.1, src.shape)
    w = rng.uniform(0.5, 2.0, 12)
    wn = w / w.sum()
    mu_s, mu_d = wn @ src, wn @ dst
    a, b = src - mu_s, dst - mu_d
    theta = np.arctan2(wn @ (a[:, 0] * b[:, 1]) - wn @ (a[:, 1] * b[:, 0]),
                       wn @ (a[:, 0] * b[:, 0]) + wn @ (a[:, 1] * b[:, 1]))
    t = mu_d - np.array([np.cos(theta) * mu_s[0] - np.sin(theta) * mu_s[1],
                         np.sin(theta) * mu_s[0] + np.cos(theta) * mu_s[1]])
    np.testing.assert_allclose(fit_se2(src, dst, w), [*t, theta], rtol=0, atol=1e-12)
    np.testing.assert_allclose(fit_se2(src, dst)[:2], pose[:2], atol=0.2)


def numpy_node_similarity(ego_desc, own_desc, tol):
    """The dense float32 formulation of FreeAlign's node similarity."""
    a, b = ego_desc.astype(np.float32), own_desc.astype(np.float32)
    diff = np.abs(a[:, None, :, None] - b[None, :, None, :])
    return (diff <= tol).any(axis=3).sum(axis=2).astype(float)


def numpy_common_subgraph(ego_d, own_d, seed, tol, yaw_ok, max_nodes):
    """The array formulation of the greedy growth (candidates updated all at once)."""
    i, k = seed
    error = np.abs(ego_d[i][:, None] - own_d[k][None, :])
    ok = error <= tol
    ok[i, :] = False
    ok[:, k] = False
    if yaw_ok is not None:
        ok &= yaw_ok
    rows, cols = np.nonzero(ok)
    order = np.argsort(error[rows, cols], kind="stable")
    rows, cols = rows[order], cols[order]
    alive = np.ones(rows.size, dtype=bool)
    nodes_e, nodes_o = [i], [k]
    while max_nodes is None or len(nodes_e) < max_nodes:
        live = np.flatnonzero(alive)
        if live.size == 0:
            break
        r, c = int(rows[live[0]]), int(cols[live[0]])
        nodes_e.append(r)
        nodes_o.append(c)
        alive[live] = (np.abs(ego_d[rows[live], r] - own_d[cols[live], c]) <= tol) & (
            rows[live] != r) & (cols[live] != c)
    return np.array(nodes_e), np.array(nodes_o)


@pytest.mark.parametrize("seed", range(10))
def test_freealign_kernels_match_the_numpy_path(seed):
    from scipy.spatial.distance import cdist

    from roco_env.policies.freealign import _descriptors, _node_similarity, common_subgraph

    rng = np.random.default_rng(seed)
    ego = random_boxes(rng, 50)
    perm = rng.permutation(50)[:35]
    own = ego[perm] + rng.normal(0, [0.3, 0.3, 0.05], (35, 3))
    own = np.vstack([own, random_boxes(rng, 8)])
    ego_d, own_d = cdist(ego[:, :2], ego[:, :2]), cdist(own[:, :2], own[:, :2])
    ego_desc, own_desc = _descriptors(ego_d, 6), _descriptors(own_d, 6)
    np.testing.assert_array_equal(_node_similarity(ego_desc, own_desc, 0.8),
                                  numpy_node_similarity(ego_desc, own_desc, 0.8))
    yaw_tol = np.deg2rad(15.0)
    grown = 0
    for i, k in [(int(perm[0]), 0), (int(perm[5]), 5), (3, 7), (int(rng.integers(50)), 40)]:
        yaw_ok = axial_difference((ego[:, 2] - ego[i, 2])[:, None],
                                  (own[:, 2] - own[k, 2])[None, :]) <= yaw_tol
        for headings, ok, cap in [(None, None, None),
                                  ((ego[:, 2], own[:, 2], yaw_tol), yaw_ok, 16)]:
            got = common_subgraph(ego_d, own_d, (i, k), 0.8, headings, cap)
            want = numpy_common_subgraph(ego_d, own_d, (i, k), 0.8, ok, cap)
            np.testing.assert_array_equal(got[0], want[0])
            np.testing.assert_array_equal(got[1], want[1])
            grown = max(grown, got[0].size)
    assert grown >= 10  # a true seed grows a large subgraph


def test_odist_scores_match_the_matrix_formulation():
    """The compiled overall distance against the quadratic-form matrix products it
    replaced (float64 here, so they agree to rounding)."""
    from roco_env.policies.v2i_calib import V2ICalibParams, _local_neighbours, _odist

    rng = np.random.default_rng(0)
    boxes = np.zeros((40, 7))
    boxes[:, [0, 1, 6]] = random_boxes(rng, 40, extent=20.0)
    own = boxes[rng.permutation(40)[:30]].copy()
    own[:, [0, 1]] += rng.normal(0, 0.3, (30, 2))
    p = V2ICalibParams()
    ego_local, _ = _local_neighbours(boxes, p.neighbors)
    own_local, _ = _local_neighbours(own, p.neighbors)
    m, n, _ = ego_local.shape
    k, q, _ = own_local.shape
    a = ego_local[..., :2].reshape(-1, 2)
    b = own_local.transpose(1, 0, 2)[..., :2].reshape(-1, 2)
    inv_r2 = 1.0 / p.odist_threshold**2
    cross = 2.0 * inv_r2 * (a @ b.T)
    base = (1.0 - inv_r2 * (a * a).sum(1))[:, None] - (inv_r2 * (b * b).sum(1))[None, :]
    yaw_b = own_local.transpose(1, 0, 2)[..., 2].reshape(-1)
    gated = axial_difference(ego_local[..., 2].reshape(-1)[:, None], yaw_b[None, :]) > (
        np.deg2rad(p.inlier_yaw_deg))
    base[gated] = -np.inf
    want = [np.maximum(sim, 0.0).reshape(m, n, q, k).max(axis=2).sum(axis=1)
            for sim in (base + cross, base - cross)]
    got = _odist(ego_local, own_local, p)
    assert want[0].max() > 3  # true anchors score several agreeing neighbours
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(g, w, rtol=0, atol=1e-9)


def numpy_fit(src, dst):
    """Unweighted closed-form SE(2) fit dst ~= T src."""
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - mu_s, dst - mu_d
    theta = np.arctan2((a[:, 0] * b[:, 1]).sum() - (a[:, 1] * b[:, 0]).sum(),
                       (a[:, 0] * b[:, 0]).sum() + (a[:, 1] * b[:, 1]).sum())
    c, s = np.cos(theta), np.sin(theta)
    return np.array([mu_d[0] - (c * mu_s[0] - s * mu_s[1]),
                     mu_d[1] - (s * mu_s[0] + c * mu_s[1]), theta])


@pytest.mark.parametrize("spacing", [2.5, 6.0])
@pytest.mark.parametrize("seed", range(5))
def test_refinement_matches_the_numpy_rounds(seed, spacing):
    """Rounds of association + fit, compiled or with the Hungarian where boxes compete
    (2.5 m rows under a 3 m gate), against the plain loop."""
    from roco_env.policies.prior_free import PriorFreeParams, refine_pose

    rng = np.random.default_rng(seed)
    gx, gy = np.meshgrid(np.arange(12) * spacing, np.arange(3) * 7.0)
    ego = np.column_stack([gx.ravel(), gy.ravel(), np.full(36, np.pi / 2)])
    ego[:, :2] += rng.normal(0, 0.1, (36, 2))
    true = np.array([1.0, -2.0, 0.05])
    c, s = np.cos(-true[2]), np.sin(-true[2])
    shifted = ego[:, :2] - true[:2]
    own = np.column_stack([c * shifted[:, 0] - s * shifted[:, 1],
                           s * shifted[:, 0] + c * shifted[:, 1], ego[:, 2] - true[2]])
    own[:, :2] += rng.normal(0, 0.1, (36, 2))
    p = PriorFreeParams()
    competed = False
    for start in [true + [0.8, 0.5, 0.02], true + rng.normal(0, [1.0, 1.0, 0.03]), true]:
        want = start.copy()
        for _ in range(p.refine_iterations):
            e, o, _ = numpy_associate(want, ego, own, p.refine_gate,
                                      np.deg2rad(p.inlier_yaw_deg))
            c, s = np.cos(want[2]), np.sin(want[2])
            mapped = own[:, :2] @ np.array([[c, s], [-s, c]]) + want[:2]
            near = np.hypot(*(ego[:, None, :2] - mapped[None]).transpose(2, 0, 1))
            competed |= bool(((near <= p.refine_gate).sum(axis=1) > 1).any())
            if e.size < 2:
                break
            new = numpy_fit(own[o, :2], ego[e, :2])
            if np.abs(new - want).max() <= 1e-6:
                break
            want = new
        np.testing.assert_allclose(refine_pose(start, ego, own, p), want, rtol=0, atol=1e-9)
    assert competed == (spacing < p.refine_gate)


@pytest.mark.parametrize("seed", range(5))
def test_suppression_matches_the_array_loop(seed):
    from roco_env.policies.prior_free import PriorFreeParams, distinct_top, poses_distinct

    rng = np.random.default_rng(seed)
    # Clusters of near-identical poses (yaws straddling +-pi) and ties in the scores.
    centres = np.column_stack([rng.uniform(-3, 3, (6, 2)), rng.choice([np.pi - 0.005, 0.3], 6)])
    poses = centres[rng.integers(0, 6, 200)] + rng.normal(0, [0.2, 0.2, 0.01], (200, 3))
    poses[:, 2] = np.mod(poses[:, 2] + np.pi, 2 * np.pi) - np.pi
    scores = rng.integers(0, 8, 200).astype(float)
    p = PriorFreeParams()
    for count in (1, 3, 50):
        kept, alive = [], np.ones(200, dtype=bool)
        order = np.argsort(-scores, kind="stable")
        while len(kept) < count and alive.any():
            kept.append(int(order[alive[order]][0]))
            alive &= poses_distinct(poses, poses[kept[-1]], p)
        np.testing.assert_array_equal(distinct_top(poses, scores, count, p), kept)
    assert len(kept) > 3  # clusters survive as separate hypotheses
