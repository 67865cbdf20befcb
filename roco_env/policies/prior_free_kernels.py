"""Compiled (numba) loops of the prior-free aligners (:mod:`roco_env.policies.prior_free`).

Each replaces a handful of numpy passes over small arrays whose per-call overhead
dominated the aligners' time (cProfile at 5 agents x 60 boxes: the association ran
~14 times per collaborator, RANSAC scored 200 hypotheses x 24 boxes by k-d tree).
Poses are (x, y, yaw) in metres and radians; the callers pass cos / sin of the
rotations computed by numpy, so the mapped centres are the numpy path's to the bit.
The numpy formulations they replace are checked against them in
tests/test_prior_free_kernels.py.

Their inputs come as small records defined here (``typing.NamedTuple``): the gates of an
association (:class:`Gates`), poses with the cos / sin of their yaws
(:class:`Placement`), a set of box pairs' invariants (:class:`PairInvariants`) and a
graph of boxes (:class:`NodeGraph`). From Python a record is passed as a plain tuple,
``tuple(record)``, which numba types in C (a named tuple it types field by field in
Python on every call: docs/performance.md), and named again on entry. Every compiled function
here calls only functions and records of this module (numba's on-disk cache notices edits
to a function's own file only).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

__all__ = ["Gates", "NodeGraph", "PairInvariants", "Placement", "axial_within",
           "descriptor_similarity", "fit_se2_kernel", "gated_pairs", "grow_subgraph",
           "inlier_counts", "matching_pairs", "odist_scores", "refine_rounds", "suppress"]


class Gates(NamedTuple):
    """How close two boxes must be: ``distance`` (m) and ``yaw`` (rad, modulo pi; < 0: no
    heading gate)."""

    distance: float
    yaw: float


class Placement(NamedTuple):
    """SE(2) poses that place boxes: x, y (m), the cos and sin of the yaw (computed by
    numpy, so the placed centres are the numpy path's to the bit) and the yaw (rad);
    floats for one pose, (H,) arrays for H."""

    x: np.ndarray
    y: np.ndarray
    cos: np.ndarray
    sin: np.ndarray
    yaw: np.ndarray


class PairInvariants(NamedTuple):
    """Pairs of one agent's boxes (P,): centre distance (m), relative heading and the
    bearing of the second box seen from the first (rad)."""

    length: np.ndarray
    relative: np.ndarray
    bearing: np.ndarray


class NodeGraph(NamedTuple):
    """One agent's boxes as a graph: centre distances (M, M) (m) and headings (M,) (rad)."""

    distances: np.ndarray
    yaw: np.ndarray


@njit(cache=True)
def axial_within(a: float, b: float, gate: float) -> bool:
    """Whether headings a and b (rad) differ by at most ``gate`` modulo pi."""
    d = (a - b) % np.pi
    return min(d, np.pi - d) <= gate


@njit(cache=True)
def gated_pairs(pose, ego, own, gates):
    """Box pairs within the :class:`Gates` under the pose (a :class:`Placement` of one
    pose): ego box i and own box k mapped by the pose within ``gates.distance`` m, and
    (``gates.yaw`` >= 0) headings within ``gates.yaw`` rad modulo pi.

    ego (M, 3), own (K, 3) box poses. Returns (ego index (P,), own index (P,), squared
    distance (P,), one_to_one) in row-major (ego, then own) order; one_to_one tells
    whether no box appears twice.
    """
    pose, gates = Placement(*pose), Gates(*gates)
    tx, ty, c, s, yaw = pose.x, pose.y, pose.cos, pose.sin, pose.yaw
    gate, yaw_gate = gates.distance, gates.yaw
    m, k = ego.shape[0], own.shape[0]
    x = np.empty(k)
    y = np.empty(k)
    for j in range(k):
        x[j] = tx + c * own[j, 0] - s * own[j, 1]
        y[j] = ty + s * own[j, 0] + c * own[j, 1]
    rows = np.empty(m * k, dtype=np.int64)
    cols = np.empty(m * k, dtype=np.int64)
    dist2 = np.empty(m * k)
    used = np.zeros(k, dtype=np.int64)
    unique = True
    count = 0
    gate2 = gate * gate
    for i in range(m):
        in_row = 0
        for j in range(k):
            dx = ego[i, 0] - x[j]
            dy = ego[i, 1] - y[j]
            d2 = dx * dx + dy * dy
            if d2 > gate2:
                continue
            if yaw_gate >= 0.0 and not axial_within(ego[i, 2], own[j, 2] + yaw, yaw_gate):
                continue
            rows[count] = i
            cols[count] = j
            dist2[count] = d2
            count += 1
            in_row += 1
            used[j] += 1
            if in_row > 1 or used[j] > 1:
                unique = False
    return rows[:count], cols[:count], dist2[:count], unique


@njit(cache=True)
def inlier_counts(poses, ego, own, gates):
    """Inliers (H,) per hypothesis (a :class:`Placement` of H poses): own boxes (K, 3)
    whose mapped centre has its nearest ego box (M, 3) within ``gates.distance`` m (the
    lowest index among equally near ones) and that box's heading within ``gates.yaw`` rad
    modulo pi. Not one-to-one: the usual RANSAC score."""
    poses, gates = Placement(*poses), Gates(*gates)
    tx, ty, c, s, yaw = poses.x, poses.y, poses.cos, poses.sin, poses.yaw
    gate, yaw_gate = gates.distance, gates.yaw
    order = np.argsort(ego[:, 0])
    ex = ego[order, 0]
    gate2 = gate * gate
    out = np.zeros(tx.size, dtype=np.int64)
    for h in range(tx.size):
        n = 0
        for j in range(own.shape[0]):
            x = tx[h] + c[h] * own[j, 0] - s[h] * own[j, 1]
            y = ty[h] + s[h] * own[j, 0] + c[h] * own[j, 1]
            lo = np.searchsorted(ex, x - gate)
            best, best_d2 = -1, math.inf
            for q in range(lo, ex.size):
                if ex[q] > x + gate:
                    break
                i = order[q]
                dx = ego[i, 0] - x
                dy = ego[i, 1] - y
                d2 = dx * dx + dy * dy
                if d2 <= gate2 and (d2 < best_d2 or (d2 == best_d2 and i < best)):
                    best, best_d2 = i, d2
            if best >= 0 and axial_within(ego[best, 2], yaw[h] + own[j, 2], yaw_gate):
                n += 1
        out[h] = n
    return out


@njit(cache=True)
def fit_se2_kernel(src, dst, w):
    """Weighted least-squares SE(2) pose (x, y, yaw) with dst ~= T * src, points (P, 2),
    weights (P,) summing to 1 (see :func:`roco_env.policies.prior_free.fit_se2`)."""
    p = src.shape[0]
    ms0 = ms1 = md0 = md1 = 0.0
    for q in range(p):
        ms0 += w[q] * src[q, 0]
        ms1 += w[q] * src[q, 1]
        md0 += w[q] * dst[q, 0]
        md1 += w[q] * dst[q, 1]
    sxx = syy = sxy = syx = 0.0
    for q in range(p):
        s0, s1 = src[q, 0] - ms0, src[q, 1] - ms1
        d0, d1 = dst[q, 0] - md0, dst[q, 1] - md1
        sxx += w[q] * (s0 * d0)
        syy += w[q] * (s1 * d1)
        sxy += w[q] * (s0 * d1)
        syx += w[q] * (s1 * d0)
    theta = math.atan2(sxy - syx, sxx + syy)
    c, s = math.cos(theta), math.sin(theta)
    out = np.empty(3)
    out[0] = md0 - (c * ms0 - s * ms1)
    out[1] = md1 - (s * ms0 + c * ms1)
    out[2] = theta
    return out


@njit(cache=True)
def matching_pairs(ego, order, own, tolerance):
    """RANSAC's consistent samples: (ego pair index (S,), own pair index (S,)) of every
    ego pair whose length is within ``tolerance.distance`` m of an own pair's, and
    (``tolerance.yaw`` >= 0) whose relative heading and bearing agree within
    ``tolerance.yaw`` rad modulo pi (a :class:`Gates`).

    ego (E,) / own (C,): the :class:`PairInvariants`, the ego's sorted by increasing
    length (once per frame, by the caller); ``order`` (E,): each sorted ego pair's index
    among the ego pairs (the index returned). Order: by own pair, then by ego length (the
    order of a searchsorted range per own pair).
    """
    ego, own, tolerance = PairInvariants(*ego), PairInvariants(*own), Gates(*tolerance)
    elen_sorted, erel_sorted, ebear_sorted = ego.length, ego.relative, ego.bearing
    clen, crel, cbear = own.length, own.relative, own.bearing
    tol, yaw_tol = tolerance.distance, tolerance.yaw
    ego_idx = []
    own_idx = []
    for j in range(clen.size):
        low, high = clen[j] - tol, clen[j] + tol
        q = np.searchsorted(elen_sorted, low)
        while q < elen_sorted.size and elen_sorted[q] <= high:
            if yaw_tol < 0.0 or (axial_within(erel_sorted[q], crel[j], yaw_tol)
                                 and axial_within(ebear_sorted[q], cbear[j], yaw_tol)):
                ego_idx.append(order[q])
                own_idx.append(j)
            q += 1
    return np.array(ego_idx, dtype=np.int64), np.array(own_idx, dtype=np.int64)


@njit(cache=True)
def descriptor_similarity(ego_desc, own_desc, tol):
    """FreeAlign's node similarity (M, K): how many of ego node i's descriptor distances
    (row i of ``ego_desc`` (M, n), float32) have a distance of collaborator node k
    (``own_desc`` (K, n), float32) within ``tol`` (float32) m; NaN padding never
    matches. float32 throughout, as the numpy formulation."""
    m, n = ego_desc.shape
    k, q = own_desc.shape
    out = np.zeros((m, k))
    for i in range(m):
        for j in range(k):
            count = 0
            for a in range(n):
                for b in range(q):
                    if abs(ego_desc[i, a] - own_desc[j, b]) <= tol:
                        count += 1
                        break
            out[i, j] = count
    return out


@njit(cache=True)
def grow_subgraph(ego, own, seed, tolerance, max_nodes):
    """FreeAlign's greedy common-subgraph growth from the seed pair (i, k) (see
    :func:`roco_env.policies.freealign.common_subgraph`).

    ego / own: the :class:`NodeGraph` of the ego's (M) and the collaborator's (K) boxes.
    Candidate pairs (r, c), r != i, c != k, with |ego_d[i, r] - own_d[k, c]| <=
    ``tolerance.distance`` m and (``tolerance.yaw`` >= 0) headings relative to the seed's
    within ``tolerance.yaw`` rad modulo pi, are taken in order of that error (stable:
    row-major among equals); a pair joins when its distances to every node already
    accepted agree within the distance tolerance and it reuses no box. ``max_nodes`` < 0:
    no limit. Returns (ego nodes, own nodes), seed first.
    """
    ego, own, tolerance = NodeGraph(*ego), NodeGraph(*own), Gates(*tolerance)
    ego_d, ego_yaw, own_d, own_yaw = ego.distances, ego.yaw, own.distances, own.yaw
    i, k = seed
    tol, yaw_tol = tolerance.distance, tolerance.yaw
    rows_l = []
    cols_l = []
    errs_l = []
    for r in range(ego_d.shape[0]):
        if r == i:
            continue
        for c in range(own_d.shape[0]):
            if c == k:
                continue
            e = abs(ego_d[i, r] - own_d[k, c])
            if e > tol:
                continue
            if yaw_tol >= 0.0 and not axial_within(ego_yaw[r] - ego_yaw[i],
                                                   own_yaw[c] - own_yaw[k], yaw_tol):
                continue
            rows_l.append(r)
            cols_l.append(c)
            errs_l.append(e)
    errs = np.array(errs_l, dtype=np.float64)
    order = np.argsort(errs, kind="mergesort")
    rows = np.array(rows_l, dtype=np.int64)[order]
    cols = np.array(cols_l, dtype=np.int64)[order]
    alive = np.ones(rows.size, dtype=np.bool_)
    nodes_e = [i]
    nodes_o = [k]
    start = 0
    while max_nodes < 0 or len(nodes_e) < max_nodes:
        while start < rows.size and not alive[start]:
            start += 1
        if start == rows.size:
            break
        r, c = rows[start], cols[start]
        nodes_e.append(r)
        nodes_o.append(c)
        for q in range(start, rows.size):
            if alive[q]:
                alive[q] = (abs(ego_d[rows[q], r] - own_d[cols[q], c]) <= tol
                            and rows[q] != r and cols[q] != c)
    return np.array(nodes_e, dtype=np.int64), np.array(nodes_o, dtype=np.int64)


@njit(cache=True)
def odist_scores(ego_local, own_local, ego_dir, own_dir, inv_r2, cos_gate):
    """V2I-Calib++'s overall distance for every anchor pair (i, k), unturned and turned
    by pi: sum over ego neighbours m of the best max(0, 1 - |a_m - b_n|^2 / r^2) over
    collaborator neighbours n (b_n negated when turned), pairs whose headings differ by
    more than the gate modulo pi scoring 0.

    ego_local (M, N, 3) / own_local (K, Q, 3): neighbour poses in their anchor's frame;
    ego_dir (M, N, 2) / own_dir (K, Q, 2): (cos, sin) of twice the neighbour headings
    (their dot product >= ``cos_gate`` = cos(2 gate) <=> within the gate modulo pi);
    inv_r2 = 1 / r^2 (1/m^2). Returns two (M, K) arrays.
    """
    m, n = ego_local.shape[0], ego_local.shape[1]
    k, q = own_local.shape[0], own_local.shape[1]
    plain = np.zeros((m, k))
    turned = np.zeros((m, k))
    for i in range(m):
        for j in range(k):
            total0 = 0.0
            total1 = 0.0
            for a in range(n):
                ax, ay = ego_local[i, a, 0], ego_local[i, a, 1]
                best0 = 0.0
                best1 = 0.0
                for b in range(q):
                    if ego_dir[i, a, 0] * own_dir[j, b, 0] + (
                            ego_dir[i, a, 1] * own_dir[j, b, 1]) < cos_gate:
                        continue
                    bx, by = own_local[j, b, 0], own_local[j, b, 1]
                    dx, dy = ax - bx, ay - by
                    best0 = max(best0, 1.0 - inv_r2 * (dx * dx + dy * dy))
                    dx, dy = ax + bx, ay + by
                    best1 = max(best1, 1.0 - inv_r2 * (dx * dx + dy * dy))
                total0 += best0
                total1 += best1
            plain[i, j] = total0
            turned[i, j] = total1
    return plain, turned


@njit(cache=True)
def refine_rounds(pose, ego, own, gates, rounds, assigned):
    """Up to ``rounds`` rounds of association (:func:`gated_pairs` with the
    :class:`Gates`) + SE(2) fit of the associated centres from ``pose`` (3,).

    Stops when fewer than 2 pairs associate, when the fit moves the pose by at most
    1e-6 in every component (the pose is kept), or pauses at a round whose boxes compete
    for each other: the caller makes the Hungarian assignment under the returned pose and
    goes on with it as ``assigned`` = (ego index (P,), own index (P,)), the first round's
    association (None: associate here). Returns (pose, rounds completed, paused at
    competing boxes).
    """
    pose = pose.copy()
    for done in range(rounds):
        yaw = pose[2]
        if assigned is not None and done == 0:
            rows, cols = assigned
        else:
            rows, cols, _, one_to_one = gated_pairs(
                (pose[0], pose[1], math.cos(yaw), math.sin(yaw), yaw), ego, own, gates)
            if not one_to_one:
                return pose, done, True
        if rows.size < 2:
            return pose, done + 1, False
        src = np.empty((rows.size, 2))
        dst = np.empty((rows.size, 2))
        for q in range(rows.size):
            src[q, 0], src[q, 1] = own[cols[q], 0], own[cols[q], 1]
            dst[q, 0], dst[q, 1] = ego[rows[q], 0], ego[rows[q], 1]
        new = fit_se2_kernel(src, dst, np.full(rows.size, 1.0 / rows.size))
        if max(abs(new[0] - pose[0]), abs(new[1] - pose[1]), abs(new[2] - pose[2])) <= 1e-6:
            return pose, done + 1, False
        pose = new
    return pose, rounds, False


@njit(cache=True)
def suppress(poses, order, count, distance, yaw):
    """Non-maximum suppression: up to ``count`` indices of ``poses`` (H, 3) taken in
    ``order`` (best first), each farther than ``distance`` m or ``yaw`` rad (wrapped to
    (-pi, pi]) from every pose kept before it."""
    alive = np.ones(poses.shape[0], dtype=np.bool_)
    kept = []
    q = 0
    while len(kept) < count:
        while q < order.size and not alive[order[q]]:
            q += 1
        if q == order.size:
            break
        h = order[q]
        kept.append(h)
        for j in range(poses.shape[0]):
            if alive[j]:
                turn = (poses[j, 2] - poses[h, 2] + np.pi) % (2.0 * np.pi) - np.pi
                if turn <= -np.pi:
                    turn += 2.0 * np.pi
                alive[j] = (math.hypot(poses[j, 0] - poses[h, 0], poses[j, 1] - poses[h, 1])
                            > distance or abs(turn) > yaw)
    return np.array(kept, dtype=np.int64)
