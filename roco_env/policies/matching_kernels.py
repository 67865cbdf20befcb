"""Compiled (numba) pair loop of RoCo's edge similarity.

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

__all__ = ["edge_similarity_sums", "gated_pairs"]


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
def gated_pairs(land_xy, centres, tau2):
    """Candidate pairs of the gate and the initial matches, without (L x K) temporaries.

    land_xy (L, 2), centres (K, 2) in the ego frame; distance = sqrt(dx^2 + dy^2).
    Returns (p (C,), q (C,), distance (C,)) of the pairs with distance <= tau2 in row-major
    (p, then q) order, and (leaves (H,), partner (H,)): every landmark whose nearest box
    (lowest index among equal distances) is within the gate, with that box.
    """
    n_land, n_box = land_xy.shape[0], centres.shape[0]
    count = 0
    for p in range(n_land):
        for q in range(n_box):
            dx = land_xy[p, 0] - centres[q, 0]
            dy = land_xy[p, 1] - centres[q, 1]
            if math.sqrt(dx * dx + dy * dy) <= tau2:
                count += 1
    cand_p = np.empty(count, dtype=np.int64)
    cand_q = np.empty(count, dtype=np.int64)
    dis = np.empty(count)
    leaves = np.empty(n_land, dtype=np.int64)
    partner = np.empty(n_land, dtype=np.int64)
    k = h = 0
    for p in range(n_land):
        best, best_q = math.inf, -1
        for q in range(n_box):
            dx = land_xy[p, 0] - centres[q, 0]
            dy = land_xy[p, 1] - centres[q, 1]
            d = math.sqrt(dx * dx + dy * dy)
            if d <= tau2:
                cand_p[k], cand_q[k], dis[k] = p, q, d
                k += 1
            if d < best:
                best, best_q = d, q
        if best <= tau2:
            leaves[h], partner[h] = p, best_q
            h += 1
    return cand_p, cand_q, dis, leaves[:h], partner[:h]
