"""Compiled (numba) loops of RoCo's matching (the gate search, the edge similarity, the
assignment's index compaction, the new landmarks of an accepted collaborator).

:func:`~roco_env.policies.matching._edge_similarity_from_features` scores every
candidate pair against every matched leaf; with the star graphs' neighbour radius most
(pair, leaf) combinations are not leaves of both stars, so one loop that skips them
costs a fraction of the dense (C x H) array passes (results agree to rounding: the
recorded numpy-path results of tests/test_roco_reference.py).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["committed_map", "compact_pairs", "edge_similarity", "edge_similarity_sums", "gated_pairs",
           "placed_centres", "placed_landmarks", "scored_pairs"]


@njit(cache=True)
def edge_similarity_sums(cand, leaf, cand_p, cand_q, leaves, partner, centres, radius2):
    """S_edge (C,): mean over usable leaves h of exp(-sqrt(max(cand[c] . leaf[:, h], 0))).

    cand (C, 11) / leaf (11, H): the bilinear factors of ||T_pm T_qn^{-1} - I||_F^2;
    a leaf is usable for candidate c when it is neither p nor q's partner, and (radius2
    >= 0) both centre offsets are within the radius: centres (C, 4) = (p_x, p_y, q_x,
    q_y) and leaf rows 11-14 of ``leaf`` hold (m_x, m_y, n_x, n_y). 0 without a usable leaf.
    """
    n_cand, n_leaf = cand.shape[0], leaf.shape[1]
    out = np.empty(n_cand)
    for c in range(n_cand):
        total = 0.0
        count = 0
        for h in range(n_leaf):
            if leaves[h] == cand_p[c] or partner[h] == cand_q[c]:
                continue
            if radius2 >= 0.0:
                dx, dy = centres[c, 0] - leaf[11, h], centres[c, 1] - leaf[12, h]
                if dx * dx + dy * dy > radius2:
                    continue
                dx, dy = centres[c, 2] - leaf[13, h], centres[c, 3] - leaf[14, h]
                if dx * dx + dy * dy > radius2:
                    continue
            norm2 = 0.0
            for i in range(11):
                norm2 += cand[c, i] * leaf[i, h]
            total += math.exp(-math.sqrt(max(norm2, 0.0)))
            count += 1
        out[c] = total / max(count, 1)
    return out


@njit(cache=True)
def edge_similarity(land, box, cand_p, cand_q, leaves, partner, radius2):
    """S_edge (C,) of the candidate pairs (cand_p landmark, cand_q box) given the initial
    matches (leaves (H,) landmarks m, partner (H,) their boxes n = A(m)), from the pose
    features (5, L) / (5, K) (x, y, x^2 + y^2, cos yaw, sin yaw) of the landmarks and the
    boxes: the (C, 11) candidate and (11, H) leaf factors of
    ``matching._edge_similarity_from_features`` (the same arithmetic element by element),
    summed by :func:`edge_similarity_sums`; radius2 < 0: no neighbour radius."""
    n_cand, h = cand_p.size, leaves.size
    cand = np.empty((n_cand, 11))
    centres = np.empty((n_cand, 4))
    for c in range(n_cand):
        p, q = cand_p[c], cand_q[c]
        px, py, p2, pc, ps = land[0, p], land[1, p], land[2, p], land[3, p], land[4, p]
        qx, qy, q2, qc, qs = box[0, q], box[1, q], box[2, q], box[3, q], box[4, q]
        cand[c, 0] = 1.0
        cand[c, 1] = pc * qc + ps * qs  # cos(v)
        cand[c, 2] = ps * qc - pc * qs  # sin(v)
        cand[c, 3], cand[c, 4], cand[c, 5] = px, py, p2
        cand[c, 6], cand[c, 7], cand[c, 8] = qx, qy, q2
        cand[c, 9] = px * qx + py * qy
        cand[c, 10] = py * qx - px * qy
        centres[c, 0], centres[c, 1], centres[c, 2], centres[c, 3] = px, py, qx, qy
    leaf = np.zeros((15, h))  # rows 11-14: leaf centres for the radius test
    for k in range(h):
        m, n = leaves[k], partner[k]
        mx, my, m2, mc, ms = land[0, m], land[1, m], land[2, m], land[3, m], land[4, m]
        nx, ny, n2, nc, ns = box[0, n], box[1, n], box[2, n], box[3, n], box[4, n]
        cu, su = mc * nc + ms * ns, ms * nc - mc * ns  # cos, sin of u = yaw_m - yaw_n
        rot_n_x, rot_n_y = cu * nx - su * ny, su * nx + cu * ny  # R(u) t_n
        rot_m_x, rot_m_y = mx * cu + my * su, my * cu - mx * su  # R(u)^T t_m
        leaf[0, k] = 4.0 + m2 + n2 - 2.0 * (mx * rot_n_x + my * rot_n_y)
        leaf[1, k], leaf[2, k] = -4.0 * cu, -4.0 * su
        leaf[3, k], leaf[4, k] = 2.0 * (rot_n_x - mx), 2.0 * (rot_n_y - my)
        leaf[6, k], leaf[7, k] = 2.0 * (rot_m_x - nx), 2.0 * (rot_m_y - ny)
        leaf[5, k] = leaf[8, k] = 1.0
        leaf[9, k], leaf[10, k] = -2.0 * cu, -2.0 * su
        leaf[11, k], leaf[12, k], leaf[13, k], leaf[14, k] = mx, my, nx, ny
    return edge_similarity_sums(cand, leaf, cand_p, cand_q, leaves, partner, centres, radius2)


@njit(cache=True)
def gated_pairs(land_xy, centres, tau2):
    """Candidate pairs of the gate and the initial matches, without (L x K) temporaries.

    land_xy (L, 2), centres (K, 2) in the ego frame; distance = sqrt(dx^2 + dy^2).
    Returns (p (C,), q (C,), distance (C,)) of the pairs with distance <= tau2 in row-major
    (p, then q) order, and (leaves (H,), partner (H,)): every landmark whose nearest box
    (lowest index among equal distances) is within the gate, with that box. A pair whose
    |dx| or |dy| alone exceeds the gate (by more than rounding) is skipped unmeasured; the
    boxes are sorted by x once, so each landmark scans only its window in x.
    """
    n_land, n_box = land_xy.shape[0], centres.shape[0]
    reach = tau2 * (1.0 + 1e-12)
    window = tau2 * (1.0 + 1e-6)  # holds every box within reach in x
    by_x = np.argsort(centres[:, 0])
    sorted_x = centres[by_x, 0]
    cand_p = np.empty(max(4 * n_land, 16), dtype=np.int64)
    cand_q = np.empty_like(cand_p)
    dis = np.empty(cand_p.size)
    leaves = np.empty(n_land, dtype=np.int64)
    partner = np.empty(n_land, dtype=np.int64)
    row_q = np.empty(n_box, dtype=np.int64)
    row_d = np.empty(n_box)
    k = h = 0
    for p in range(n_land):
        lx, ly = land_xy[p, 0], land_xy[p, 1]
        best, best_q, size = math.inf, -1, 0
        for w in range(np.searchsorted(sorted_x, lx - window), n_box):
            if sorted_x[w] > lx + window:
                break
            q = by_x[w]
            dx = lx - centres[q, 0]
            dy = ly - centres[q, 1]
            if abs(dx) > reach or abs(dy) > reach:
                continue  # beyond the gate: neither a pair nor a nearest box within it
            d = math.sqrt(dx * dx + dy * dy)
            if d <= tau2:  # the row's pairs, kept in increasing box order
                slot = size
                while slot and row_q[slot - 1] > q:
                    row_q[slot], row_d[slot] = row_q[slot - 1], row_d[slot - 1]
                    slot -= 1
                row_q[slot], row_d[slot] = q, d
                size += 1
            if d < best or (d == best and q < best_q):
                best, best_q = d, q
        if k + size > cand_p.size:
            grown = max(2 * cand_p.size, k + size)
            cand_p = np.concatenate((cand_p, np.empty(grown - cand_p.size, dtype=np.int64)))
            cand_q = np.concatenate((cand_q, np.empty(grown - cand_q.size, dtype=np.int64)))
            dis = np.concatenate((dis, np.empty(grown - dis.size)))
        for r in range(size):
            cand_p[k], cand_q[k], dis[k] = p, row_q[r], row_d[r]
            k += 1
        if best <= tau2:
            leaves[h], partner[h] = p, best_q
            h += 1
    return cand_p[:k].copy(), cand_q[:k].copy(), dis[:k].copy(), leaves[:h], partner[:h]


@njit(cache=True)
def _compact_axis(index):
    """The distinct values of ``index`` (C,) (non-negative), sorted, the position of each
    entry's value among them (C,), and whether every value occurs once."""
    size = 0
    for k in range(index.size):
        size = max(size, index[k] + 1)
    count = np.zeros(size, dtype=np.int64)
    for k in range(index.size):
        count[index[k]] += 1
    single = True
    position = np.empty(size, dtype=np.int64)
    n_used = 0
    for i in range(size):
        position[i] = n_used
        if count[i]:
            n_used += 1
            single = single and count[i] == 1
    used = np.empty(n_used, dtype=np.int64)
    for i in range(size):
        if count[i]:
            used[position[i]] = i
    inverse = np.empty(index.size, dtype=np.int64)
    for k in range(index.size):
        inverse[k] = position[index[k]]
    return used, inverse, single


@njit(cache=True)
def compact_pairs(cand_p, cand_q):
    """The rows and columns the candidate pairs (C,) use (non-negative indices), as
    ``np.unique`` with ``return_inverse`` gives them: (rows (R,) sorted, row index of each
    pair (C,), cols (Q,) sorted, column index of each pair (C,)), and whether every row
    and every column has a single pair."""
    rows, row_idx, single_rows = _compact_axis(cand_p)
    cols, col_idx, single_cols = _compact_axis(cand_q)
    return rows, row_idx, cols, col_idx, single_rows and single_cols


@njit(cache=True)
def placed_landmarks(pose, own, boxes):
    """The agent's boxes ``own[boxes]`` (own (K, 3) in its frame, boxes (B,) indices) placed
    in the ego frame by its pose (3,) as ``geometry.se2_compose(pose, own[boxes])`` does
    (yaw wrapped to (-pi, pi]), with their pose features (5, B) (``matching.pose_features``:
    x, y, x^2 + y^2, cos(yaw), sin(yaw))."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    poses = np.empty((boxes.size, 3))
    features = np.empty((5, boxes.size))
    for k in range(boxes.size):
        bx, by, byaw = own[boxes[k], 0], own[boxes[k], 1], own[boxes[k], 2]
        x = pose[0] + c * bx - s * by
        y = pose[1] + s * bx + c * by
        yaw = (pose[2] + byaw + math.pi) % (2.0 * math.pi) - math.pi
        if yaw <= -math.pi:
            yaw += 2.0 * math.pi
        poses[k, 0], poses[k, 1], poses[k, 2] = x, y, yaw
        features[0, k], features[1, k], features[2, k] = x, y, x * x + y * y
        features[3, k], features[4, k] = math.cos(yaw), math.sin(yaw)
    return poses, features


@njit(cache=True)
def placed_centres(pose, own):
    """The centres (K, 2) of the boxes own (K, 3) (the agent's frame) in the ego frame
    under its pose (3,) (x m, y m, yaw rad): ``R(yaw) t + (x, y)``, each coordinate as
    ``t_x * cos + t_y * (-sin)`` (y: ``t_x * sin + t_y * cos``) plus the offset. (numpy's
    ``own[:, :2] @ R^T`` goes through BLAS, whose kernels may fuse the multiply-adds:
    the same values to the last bit or two.)"""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    centres = np.empty((own.shape[0], 2))
    for k in range(own.shape[0]):
        centres[k, 0] = own[k, 0] * c + own[k, 1] * -s + pose[0]
        centres[k, 1] = own[k, 0] * s + own[k, 1] * c + pose[1]
    return centres


@njit(cache=True)
def committed_map(pose, own, covariance, match_land, match_box, agent, land_poses,
                  land_features, land_covariance, obs_agent, obs_box, obs_land):
    """RoCo's map after accepting a collaborator (``roco._commit``), in one pass: its boxes
    own (K, 3) (its frame; covariance (K, 3, 3)) matched as match_box (P,) to the landmarks
    match_land (P,) become observations, the unmatched ones (in increasing box order) new
    landmarks placed by its pose (3,) (:func:`placed_landmarks`). Returns the landmark
    poses (M', 3), features (5, M'), covariances (M', 3, 3) and the observations'
    agent, box and landmark ids (O',): the inputs with the new rows appended, as
    ``np.concatenate`` gives them (agent: the collaborator's index)."""
    unmatched = np.ones(own.shape[0], dtype=np.bool_)
    for k in range(match_box.size):
        unmatched[match_box[k]] = False
    new_boxes = np.nonzero(unmatched)[0]
    n_land, n_new, n_obs = land_poses.shape[0], new_boxes.size, obs_agent.size
    new_poses, new_features = placed_landmarks(pose, own, new_boxes)
    poses = np.concatenate((land_poses, new_poses))
    features = np.empty((5, n_land + n_new))
    features[:, :n_land] = land_features
    features[:, n_land:] = new_features
    land_cov = np.empty((n_land + n_new, 3, 3))
    land_cov[:n_land] = land_covariance
    for k in range(n_new):
        land_cov[n_land + k] = covariance[new_boxes[k]]
    size = n_obs + own.shape[0]
    agents, boxes, lands = np.empty(size, np.int64), np.empty(size, np.int64), np.empty(size, np.int64)
    agents[:n_obs], boxes[:n_obs], lands[:n_obs] = obs_agent, obs_box, obs_land
    agents[n_obs:] = agent
    for k in range(match_box.size):
        boxes[n_obs + k], lands[n_obs + k] = match_box[k], match_land[k]
    for k in range(n_new):
        boxes[n_obs + match_box.size + k], lands[n_obs + match_box.size + k] = new_boxes[k], n_land + k
    return poses, features, land_cov, agents, boxes, lands


@njit(cache=True)
def scored_pairs(land_xy, centres, tau2, lam, use_edge, land_features, box_features, radius2,
                 tau1, cached):
    """One matching of ``matching.StarGraphMatcher``: the gated candidate pairs
    (:func:`gated_pairs`) scored S = lam * S_dis (lam = 0: no distance term) + S_edge
    (with ``use_edge``, :func:`edge_similarity`; reused from ``cached`` = (cand_p, cand_q,
    leaves, partner, S_edge) of an earlier call when the pairs and the initial matches
    are the same), and the assignment's shortcut: when every landmark and every box has a
    single candidate and every score is > 0, the pairs with S >= tau1 are the assignment.

    Returns (assigned?, landmark (P,), box (P,), S (P,) of the assignment when the
    shortcut applies (else empty), then the candidates (cand_p, cand_q, S) for the full
    assignment, and the new cache (cand_p, cand_q, leaves, partner, S_edge)).
    """
    cand_p, cand_q, dis, leaves, partner = gated_pairs(land_xy, centres, tau2)
    score = np.empty(cand_p.size)
    for k in range(cand_p.size):
        score[k] = lam * math.exp(-dis[k])
    edge = cached[4]
    if use_edge:
        old_p, old_q, old_leaves, old_partner = cached[0], cached[1], cached[2], cached[3]
        same = old_p.size == cand_p.size and old_leaves.size == leaves.size
        for k in range(cand_p.size if same else 0):
            same = same and old_p[k] == cand_p[k] and old_q[k] == cand_q[k]
        for k in range(leaves.size if same else 0):
            same = same and old_leaves[k] == leaves[k] and old_partner[k] == partner[k]
        if not same:
            edge = edge_similarity(land_features, box_features, cand_p, cand_q, leaves, partner,
                                   radius2)
        for k in range(cand_p.size):
            score[k] = score[k] + edge[k]
    single = compact_pairs(cand_p, cand_q)[4]
    for k in range(cand_p.size):
        single = single and score[k] > 0
    kept = np.zeros(cand_p.size, dtype=np.bool_)
    if single:
        for k in range(cand_p.size):
            kept[k] = score[k] >= tau1
    return (single, cand_p[kept], cand_q[kept], score[kept], cand_p, cand_q, score,
            (cand_p, cand_q, leaves, partner, edge))
