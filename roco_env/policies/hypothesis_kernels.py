"""Compiled (numba) loops of the aliasing-aware hypotheses (:mod:`roco_env.policies.hypotheses`).

A roco_antialias call votes, refines and scores pose hypotheses for every collaborator;
in numpy each of those stages is tens of array operations on a few hundred box pairs,
whose fixed call overhead dominated the call (about half of it at 10 agents and 200
objects). Here the box pairing, the rotation vote, the translation vote grid, its peak
scan and the evidence and margin of the hypotheses run compiled (the refinement is
:func:`~roco_env.policies.pose_kernels.refine_starts`), element by element with the
array path's arithmetic in the same order: the votes are accumulated pair by pair as
``np.bincount`` does, the grid's 3x3 box sum adds the shifted cells in the order of the
array path, and the evidence sums the selected gains with numpy's pairwise summation
(:func:`pairwise_sum`), so the results are those of the array path to the bit
(tests/test_hypothesis_kernels.py keeps that path as the reference). Poses are (x m, y m,
yaw rad).

The kernels take an agent's boxes as a :class:`BoxTerms` record, the evidence settings as
an :class:`EvidenceSettings` and the votes' as a :class:`VoteSettings`
(``typing.NamedTuple``, compiled as tuples with named fields); from Python a record is
passed as a plain tuple, ``tuple(record)``, which numba types in C (a named tuple it types
field by field in Python on every call: docs/performance.md), and named again on entry.

Every compiled function here calls only functions and records of this module: numba's
on-disk cache recompiles a function when its own file changes, not when a callee in
another file does.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

__all__ = ["BoxTerms", "EvidenceSettings", "VoteSettings", "best_pair_gains", "close_pairs",
           "decision_margin", "hypothesis_scores", "pairwise_sum", "rotation_votes",
           "translation_votes", "vote_peaks"]

_HALF_PI = math.pi / 2


class BoxTerms(NamedTuple):
    """One agent's boxes as the evidence reads them (``hypotheses.BoxSet``): poses (K, 3)
    in its own frame, log sizes (K, 3) (l, w, h), var_t (K,) the mean of the centre's x
    and y variances (m^2), var_r (K,) the heading variance (rad^2), and ``range`` (m) the
    radius of its observed disk."""

    poses: np.ndarray
    log_sizes: np.ndarray
    var_t: np.ndarray
    var_r: np.ndarray
    range: float


class EvidenceSettings(NamedTuple):
    """The evidence's settings (``hypotheses.evidence_terms``): the pose slack variances
    slack_t (m^2) and slack_r (rad^2), 2 size_sigma^2 (0: sizes not used), outlier_chi2,
    free_space_penalty, and the switches of the free-space and mutual-detection terms."""

    slack_t: float
    slack_r: float
    size_denominator: float
    outlier_chi2: float
    free_space_penalty: float
    use_free_space: bool
    use_mutual_detection: bool


class VoteSettings(NamedTuple):
    """The votes' settings (``hypotheses._vote_settings``): the rotation search's
    half-width ``half`` and cell (rad), its bin count and pair radius (m); the translation
    grid's pair radius (m), search half-width (m), cell ``vote_bin`` (m) and cells per
    axis; 2 size_sigma^2 (0: sizes not used); the heading std weighing the translation
    votes (rad); the peaks' suppression radius (cells^2), the most peaks kept and the
    share of the strongest vote a peak needs."""

    half: float
    cell: float
    bins: int
    rotation_radius: float
    radius: float
    search_radius: float
    vote_bin: float
    cells: int
    size_denominator: float
    yaw_sigma: float
    suppress: float
    max_hypotheses: int
    vote_floor: float


@njit(cache=True)
def close_pairs(a_xy, b_xy, radius):
    """(index into a (P,), index into b (P,)) of every pair of centres a_xy (A, 2),
    b_xy (B, 2) at most ``radius`` apart (distance sqrt(dx^2 + dy^2)), in row-major order.

    Only the b centres within the radius in x (with a margin far above rounding) are
    measured: b is sorted by x once and each row scans its window, its pairs then put
    back in index order."""
    n_a, n_b = a_xy.shape[0], b_xy.shape[0]
    by_x = np.argsort(b_xy[:, 0])
    sorted_x = b_xy[by_x, 0]
    reach = radius * (1.0 + 1e-6)
    first = np.empty(max(8 * n_a, 16), dtype=np.int64)
    second = np.empty_like(first)
    window = np.empty(n_b, dtype=np.int64)
    count = 0
    for i in range(n_a):
        ax, ay = a_xy[i, 0], a_xy[i, 1]
        size = 0
        for k in range(np.searchsorted(sorted_x, ax - reach), n_b):
            if sorted_x[k] > ax + reach:
                break
            j = by_x[k]
            dx, dy = ax - b_xy[j, 0], ay - b_xy[j, 1]
            if math.sqrt(dx * dx + dy * dy) <= radius:
                # Insertion into the row's pairs, kept in increasing index order.
                slot = size
                while slot and window[slot - 1] > j:
                    window[slot] = window[slot - 1]
                    slot -= 1
                window[slot] = j
                size += 1
        if count + size > first.size:
            grown = max(2 * first.size, count + size)
            first = np.concatenate((first, np.empty(grown - first.size, dtype=np.int64)))
            second = np.concatenate((second, np.empty(grown - second.size, dtype=np.int64)))
        for k in range(size):
            first[count + k], second[count + k] = i, window[k]
        count += size
    return first[:count].copy(), second[:count].copy()


@njit(cache=True)
def best_pair_gains(ego, collab, mapped, evidence):
    """Per box, the largest gain ``outlier_chi2 - chi2`` of its pairs with the other set's
    boxes (0 without a pair that gains): (collaborator boxes (K1,), ego boxes (K0,)).

    chi2 of ego box i and collaborator box j (the :class:`BoxTerms` ego and collab, the
    collaborator's poses mapped (K1, 3) into the ego frame): |t_i - t_j|^2 / (var_t_i +
    var_t_j + slack_t) + half-turn yaw difference^2 / (var_r_i + var_r_j + slack_r) +
    (size_denominator > 0) |log size difference|^2 / size_denominator (the
    :class:`EvidenceSettings`); every pair is visited (no radius: a pair beyond it cannot
    gain)."""
    ego, collab, evidence = BoxTerms(*ego), BoxTerms(*collab), EvidenceSettings(*evidence)
    ego_poses, ego_log_sizes, ego_var_t, ego_var_r = (ego.poses, ego.log_sizes, ego.var_t,
                                                      ego.var_r)
    col_log_sizes, col_var_t, col_var_r = collab.log_sizes, collab.var_t, collab.var_r
    slack_t, slack_r, outlier_chi2 = evidence.slack_t, evidence.slack_r, evidence.outlier_chi2
    size_denominator = evidence.size_denominator
    n_ego, n_col = ego_poses.shape[0], mapped.shape[0]
    forward = np.zeros(n_col)
    backward = np.zeros(n_ego)
    half = math.pi / 2
    for i in range(n_ego):
        for j in range(n_col):
            dx = ego_poses[i, 0] - mapped[j, 0]
            dy = ego_poses[i, 1] - mapped[j, 1]
            chi2 = (dx * dx + dy * dy) / (ego_var_t[i] + col_var_t[j] + slack_t)
            if chi2 >= outlier_chi2:
                continue  # the other terms are >= 0: no gain
            dyaw = (ego_poses[i, 2] - mapped[j, 2] + half) % math.pi - half
            chi2 += dyaw * dyaw / (ego_var_r[i] + col_var_r[j] + slack_r)
            if size_denominator > 0.0:
                d0 = ego_log_sizes[i, 0] - col_log_sizes[j, 0]
                d1 = ego_log_sizes[i, 1] - col_log_sizes[j, 1]
                d2 = ego_log_sizes[i, 2] - col_log_sizes[j, 2]
                chi2 += (d0 * d0 + d1 * d1 + d2 * d2) / size_denominator
            gain = outlier_chi2 - chi2
            if gain > 0.0:
                forward[j] = max(forward[j], gain)
                backward[i] = max(backward[i], gain)
    return forward, backward


@njit(cache=True)
def _block_sum(values, start, count):
    """numpy's pairwise sum of a run of at most 128 values: below 8 one by one, else 8
    accumulators combined pairwise, then the remainder one by one."""
    if count < 8:
        total = 0.0
        for k in range(start, start + count):
            total += values[k]
        return total
    acc = values[start : start + 8].copy()
    k = 8
    while k < count - count % 8:
        for lane in range(8):
            acc[lane] += values[start + k + lane]
        k += 8
    total = ((acc[0] + acc[1]) + (acc[2] + acc[3])) + ((acc[4] + acc[5]) + (acc[6] + acc[7]))
    while k < count:
        total += values[start + k]
        k += 1
    return total


@njit(cache=True)
def pairwise_sum(values, start, count):
    """Sum of ``values[start:start + count]`` in numpy's pairwise order (``ndarray.sum``
    of a contiguous float64 array): runs of up to 128 by :func:`_block_sum`, longer runs
    split in two, the first part a multiple of 8 long, and the two sums added. Evaluated
    with an explicit stack (numba's cache does not hold recursive functions reliably)."""
    if count <= 128:
        return _block_sum(values, start, count)
    # Tasks (start, count, combine?): a split pushes its combination, then its second
    # and first parts, so the first part is summed first and the two sums are added last.
    tasks = np.empty((128, 3), dtype=np.int64)
    sums = np.empty(64)
    tasks[0, 0], tasks[0, 1], tasks[0, 2] = start, count, 0
    n_tasks, n_sums = 1, 0
    while n_tasks:
        n_tasks -= 1
        first, size, combine = tasks[n_tasks, 0], tasks[n_tasks, 1], tasks[n_tasks, 2]
        if combine:
            n_sums -= 1
            sums[n_sums - 1] = sums[n_sums - 1] + sums[n_sums]
        elif size <= 128:
            sums[n_sums] = _block_sum(values, first, size)
            n_sums += 1
        else:
            half = size // 2
            half -= half % 8
            tasks[n_tasks, 0], tasks[n_tasks, 1], tasks[n_tasks, 2] = first, size, 1
            tasks[n_tasks + 1, 0], tasks[n_tasks + 1, 1] = first + half, size - half
            tasks[n_tasks + 2, 0], tasks[n_tasks + 2, 1] = first, half
            tasks[n_tasks + 1, 2] = tasks[n_tasks + 2, 2] = 0
            n_tasks += 3
    return sums[0]


@njit(cache=True)
def _mapped(pose, poses):
    """Poses (K, 3) moved by the SE(2) pose (3,), heading not wrapped."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    out = np.empty_like(poses)
    for k in range(poses.shape[0]):
        out[k, 0] = c * poses[k, 0] - s * poses[k, 1] + pose[0]
        out[k, 1] = s * poses[k, 0] + c * poses[k, 1] + pose[1]
        out[k, 2] = poses[k, 2] + pose[2]
    return out


@njit(cache=True)
def _half_turn(angle):
    """Angle modulo pi in [-pi/2, pi/2) (detected headings may be flipped)."""
    return (angle + _HALF_PI) % math.pi - _HALF_PI


@njit(cache=True)
def _size_weight(ego_log_sizes, col_log_sizes, i, j, size_denominator):
    """exp(-chi2 / 2) of the log-size difference of ego box i and collaborator box j
    (both boxes noisy); 1 when sizes are not used (size_denominator 0)."""
    if size_denominator <= 0.0:
        return 1.0
    d0 = ego_log_sizes[i, 0] - col_log_sizes[j, 0]
    d1 = ego_log_sizes[i, 1] - col_log_sizes[j, 1]
    d2 = ego_log_sizes[i, 2] - col_log_sizes[j, 2]
    return math.exp(-0.5 * ((d0 * d0 + d1 * d1 + d2 * d2) / size_denominator))


@njit(cache=True)
def rotation_votes(ego, collab, reported, votes):
    """Weighted votes (bins,) of the heading differences (modulo pi) of the box pairs
    (:class:`BoxTerms` ego and collab) whose centres lie within ``rotation_radius`` m under
    the reported pose (3,): bin of ``(dyaw + half) / cell`` (last bin for the upper edge),
    pairs with |dyaw| > half left out, each weighted by its size likelihood; and the number
    of pairs within the radius (0: nothing to vote). votes: :class:`VoteSettings`."""
    ego, collab, votes = BoxTerms(*ego), BoxTerms(*collab), VoteSettings(*votes)
    ego_poses, ego_log_sizes, col_log_sizes = ego.poses, ego.log_sizes, collab.log_sizes
    half, cell, bins, size_denominator = votes.half, votes.cell, votes.bins, votes.size_denominator
    radius = votes.rotation_radius
    mapped = _mapped(reported, collab.poses)
    first, second = close_pairs(ego_poses[:, :2], mapped[:, :2], radius)
    counts = np.zeros(bins)
    for k in range(first.size):
        i, j = first[k], second[k]
        dyaw = _half_turn(ego_poses[i, 2] - mapped[j, 2])
        if abs(dyaw) <= half:
            weight = _size_weight(ego_log_sizes, col_log_sizes, i, j, size_denominator)
            counts[min(np.int64((dyaw + half) / cell), bins - 1)] += weight
    return counts, first.size


@njit(cache=True)
def translation_votes(ego, collab, rotated, votes):
    """3x3-box-smoothed grid (cells, cells) of the centre offsets (ego minus collaborator,
    within ``search_radius`` m per axis) of the box pairs (:class:`BoxTerms` ego and
    collab) within ``radius`` m under the rotated pose (3,), ``vote_bin`` m cells; each pair
    weighted by its size likelihood and exp(-(dyaw / yaw_sigma)^2 / 2) of its heading
    difference modulo pi (rad). votes: :class:`VoteSettings`."""
    ego, collab, votes = BoxTerms(*ego), BoxTerms(*collab), VoteSettings(*votes)
    ego_poses, ego_log_sizes, col_log_sizes = ego.poses, ego.log_sizes, collab.log_sizes
    radius, search_radius, vote_bin = votes.radius, votes.search_radius, votes.vote_bin
    cells, size_denominator, yaw_sigma = votes.cells, votes.size_denominator, votes.yaw_sigma
    mapped = _mapped(rotated, collab.poses)
    first, second = close_pairs(ego_poses[:, :2], mapped[:, :2], radius)
    padded = np.zeros((cells + 2, cells + 2))
    for k in range(first.size):
        i, j = first[k], second[k]
        dx = ego_poses[i, 0] - mapped[j, 0]
        dy = ego_poses[i, 1] - mapped[j, 1]
        if abs(dx) > search_radius or abs(dy) > search_radius:
            continue
        dyaw = _half_turn(ego_poses[i, 2] - mapped[j, 2])
        scaled = dyaw / yaw_sigma
        weight = _size_weight(ego_log_sizes, col_log_sizes, i, j, size_denominator) * math.exp(
            -0.5 * (scaled * scaled)
        )
        ix = min(np.int64((dx + search_radius) / vote_bin), cells - 1)
        iy = min(np.int64((dy + search_radius) / vote_bin), cells - 1)
        padded[ix + 1, iy + 1] += weight
    smooth = np.empty((cells, cells))
    for x in range(cells):
        for y in range(cells):
            total = padded[x, y]
            for a in range(3):
                for b in range(3):
                    if a or b:
                        total += padded[x + a, y + b]
            smooth[x, y] = total
    return smooth


@njit(cache=True)
def vote_peaks(smooth, order, rotated, votes):
    """Hypotheses (H, 3) at the peaks of the smoothed translation votes (cells, cells):
    cells in ``order`` (decreasing votes, as ``np.argsort(-smooth, axis=None)`` gives them)
    until ``max_hypotheses`` are found or the votes fall to ``vote_floor`` of the
    strongest (or 0); a cell within ``suppress`` (cells^2) of an earlier peak is skipped
    (:class:`VoteSettings`). Each peak moves the rotated pose (3,) by its cell centre's
    offset (m)."""
    votes = VoteSettings(*votes)
    max_hypotheses, vote_floor, suppress = votes.max_hypotheses, votes.vote_floor, votes.suppress
    vote_bin, search_radius = votes.vote_bin, votes.search_radius
    cells = smooth.shape[1]
    flat_votes = smooth.ravel()
    floor = max(vote_floor * smooth.max(), 0.0)
    peaks = np.empty((max_hypotheses, 2), dtype=np.int64)
    count = 0
    for flat in order:
        if count == max_hypotheses or flat_votes[flat] <= floor:
            break
        a, b = flat // cells, flat % cells
        apart = True
        for k in range(count):
            apart = apart and (a - peaks[k, 0]) ** 2 + (b - peaks[k, 1]) ** 2 > suppress
        if apart:
            peaks[count, 0], peaks[count, 1] = a, b
            count += 1
    out = np.empty((count, 3))
    for k in range(count):
        out[k, 0] = rotated[0] + ((peaks[k, 0] + 0.5) * vote_bin - search_radius)
        out[k, 1] = rotated[1] + ((peaks[k, 1] + 0.5) * vote_bin - search_radius)
        out[k, 2] = rotated[2]
    return out


@njit(cache=True)
def _mutual_gain(boxes, target, unexplained, evidence):
    """Largest gain ``outlier_chi2 - chi2`` (>= 0) of the unexplained boxes (a
    :class:`BoxTerms`; ``unexplained`` (K,)) as a detection of the vehicle at ``target``
    (3,) (heading modulo pi)."""
    poses, var_t, var_r = boxes.poses, boxes.var_t, boxes.var_r
    slack_t, slack_r, outlier_chi2 = evidence.slack_t, evidence.slack_r, evidence.outlier_chi2
    best = 0.0
    for k in range(poses.shape[0]):
        dx, dy = poses[k, 0] - target[0], poses[k, 1] - target[1]
        dyaw = _half_turn(poses[k, 2] - target[2])
        chi2 = (dx * dx + dy * dy) / (var_t[k] + slack_t) + dyaw * dyaw / (var_r[k] + slack_r)
        gain = max(outlier_chi2 - chi2, 0.0) if unexplained[k] else 0.0
        best = gain if k == 0 else max(best, gain)
    return best


@njit(cache=True)
def hypothesis_scores(ego, collab, poses, evidence):
    """Evidence (H,) of each hypothesis pose (H, 3) (``hypotheses.score_hypotheses``;
    :class:`BoxTerms` ego and collab, :class:`EvidenceSettings`): the gains of the
    collaborator's boxes inside the ego's observed disk (radius ``ego.range`` m) under
    every hypothesis, with free space the ego's boxes inside the collaborator's disk (gains
    minus ``free_space_penalty`` per unexplained box), with mutual detection the two direct
    detections' gains."""
    ego, collab, evidence = BoxTerms(*ego), BoxTerms(*collab), EvidenceSettings(*evidence)
    ego_poses, col_poses, ego_range, col_range = ego.poses, collab.poses, ego.range, collab.range
    n_col, n_ego, n_hyp = col_poses.shape[0], ego_poses.shape[0], poses.shape[0]
    forward_set = np.ones(n_col, dtype=np.bool_)
    backward_set = np.ones(n_ego, dtype=np.bool_)
    for h in range(n_hyp):
        mapped = _mapped(poses[h], col_poses)
        for j in range(n_col):
            forward_set[j] &= np.hypot(mapped[j, 0], mapped[j, 1]) <= ego_range
        for i in range(n_ego):
            dx, dy = ego_poses[i, 0] - poses[h, 0], ego_poses[i, 1] - poses[h, 1]
            backward_set[i] &= np.hypot(dx, dy) <= col_range
    scores = np.zeros(n_hyp)
    selected = np.empty(max(n_col, n_ego))
    for h in range(n_hyp):
        pose = poses[h]
        forward, backward = best_pair_gains(ego, collab, _mapped(pose, col_poses), evidence)
        count = 0
        for j in range(n_col):
            if forward_set[j]:
                selected[count] = forward[j]
                count += 1
        scores[h] = pairwise_sum(selected, 0, count)
        if evidence.use_free_space:
            count = unexplained = 0
            for i in range(n_ego):
                if backward_set[i]:
                    selected[count] = backward[i]
                    count += 1
                    unexplained += backward[i] == 0
            scores[h] += pairwise_sum(selected, 0, count)
            scores[h] -= evidence.free_space_penalty * float(unexplained)
        if evidence.use_mutual_detection:
            c, s = math.cos(pose[2]), math.sin(pose[2])
            inverse = np.array([-c * pose[0] - s * pose[1], s * pose[0] - c * pose[1], -pose[2]])
            total = 0.0
            if n_ego:
                total += _mutual_gain(ego, pose, backward == 0, evidence)
            if n_col:
                total += _mutual_gain(collab, inverse, forward == 0, evidence)
            scores[h] += total
    return scores


@njit(cache=True)
def _wrap(angle):
    """``geometry.wrap_angle`` of one angle: to (-pi, pi]."""
    wrapped = (angle + math.pi) % (2.0 * math.pi) - math.pi
    return wrapped + 2.0 * math.pi if wrapped <= -math.pi else wrapped


@njit(cache=True)
def _prior_chi2(pose, centre, sigma_t2, sigma_r2):
    """Mahalanobis distance of ``pose`` from ``centre`` (3,) with variances sigma_t2 (m^2)
    in translation and sigma_r2 (rad^2) in yaw (``antialias._prior_chi2``)."""
    dx, dy = pose[0] - centre[0], pose[1] - centre[1]
    yaw = _wrap(pose[2] - centre[2])
    return (dx * dx + dy * dy) / sigma_t2 + yaw * yaw / sigma_r2


@njit(cache=True)
def decision_margin(ego, collab, poses, reported, track, evidence, priors, distinct):
    """Step 2-3 of ``roco_env.policies.antialias`` for one collaborator's refined hypotheses
    (H, 3), H >= 1: their evidence (:func:`hypothesis_scores` of the ego's and the
    collaborator's boxes, :class:`BoxTerms` ego and collab, with the
    :class:`EvidenceSettings` ``evidence``) minus the prior terms of the reported pose (3,)
    and, unless ``track`` is None, of the track's prediction ``track`` (3,), ``priors`` =
    their variances (m^2, rad^2, m^2, rad^2). Two poses are distinct when farther apart
    than ``distinct`` = (m, rad).

    Returns (index of the best hypothesis, its score minus the best distinct one's, 0
    without a distinct one), the scores (H,) and the scores without the reported pose's
    prior term (H,) (the ambiguity diagnosis finds rivals with those).
    """
    scores = hypothesis_scores(ego, collab, poses, evidence)
    count = poses.shape[0]
    unreported = scores.copy()
    for h in range(count):
        scores[h] -= _prior_chi2(poses[h], reported, priors[0], priors[1])
    if track is not None:
        for h in range(count):
            track_term = _prior_chi2(poses[h], track, priors[2], priors[3])
            scores[h] -= track_term
            unreported[h] -= track_term
    best = np.argmax(scores)
    runner_up, found = 0.0, False
    for h in range(count):
        far = np.hypot(poses[h, 0] - poses[best, 0], poses[h, 1] - poses[best, 1]) > distinct[0]
        if far or abs(_wrap(poses[h, 2] - poses[best, 2])) > distinct[1]:
            runner_up = scores[h] if not found else max(runner_up, scores[h])
            found = True
    return best, scores[best] - runner_up, scores, unreported
