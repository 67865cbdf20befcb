"""Pose hypotheses for one collaborator and their evidence (aliasing-aware alignment).

In a repetitive scene (a full parking lot: cars every 2.5 m) a collaborator's boxes
fit the ego's boxes almost equally well at several global shifts, and a matcher that
starts from the reported pose converges to whichever shift lies nearest. This module
makes the shifts explicit:

1. :func:`generate_hypotheses`: the relative rotation error is voted from the box
   headings (modulo pi) of nearby box pairs, then the translation error from their
   centre offsets on a 2D grid (a Hough vote); the ``max_hypotheses`` strongest local
   maxima within ``search_radius`` become hypotheses (plus the reported pose and any
   extra seeds, e.g. a temporal track's prediction);
2. :func:`refine_hypothesis`: nearest-neighbour matching within ``refine_gate`` and a
   robust single-vertex pose-graph solve (the solver of
   :func:`~roco_env.policies.posegraph.optimize_pose`), twice, in one compiled pass;
3. :func:`score_hypotheses`: a log-likelihood ratio per hypothesis in chi-square units
   (-2 ln L): every collaborator box explained by an ego box gains
   ``outlier_chi2 - chi2(pair)`` (position with both boxes' covariances, heading modulo pi,
   log sizes), switchable terms add the mirror image with a penalty for ego boxes left
   unexplained inside the collaborator's observed disk (free space), the mutual
   detections (an ego box where the hypothesis puts the collaborator's own vehicle, a
   collaborator box where it puts the ego); priors (the reported pose, a track) subtract
   their Mahalanobis distance. Distinctive objects need no weight of their own: the log
   sizes and headings in the pair chi2 are what makes a box distinctive, in the
   likelihood's own units (an explicit rarity weight was measured to add nothing and
   would make the margin's scale depend on the scene).

Poses are T_{j->i} (x m, y m, yaw rad) in the ego frame; boxes (K, 7) as everywhere.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from roco_env.policies.landmarks import require_positive
from roco_env.policies.matching_kernels import best_pair_gains, close_pairs
from roco_env.policies.pose_kernels import KERNEL_CODES, refine_pose
from roco_env.policies.posegraph import _MIN_DIAG

__all__ = [
    "BoxSet",
    "EvidenceParams",
    "box_set",
    "generate_hypotheses",
    "refine_hypothesis",
    "score_hypotheses",
]


# LM cap and relative-decrease stop of a refinement solve (they only steer the hypothesis).
_REFINE_ITERATIONS, _REFINE_TOLERANCE = 50, 1e-4

_POSITIVE_FIELDS = (
    "search_radius",
    "search_yaw_deg",
    "vote_bin",
    "refine_gate",
    "outlier_chi2",
    "pose_slack_t",
    "pose_slack_r_deg",
    "size_sigma",
)


@dataclass(frozen=True)
class EvidenceParams:
    """Hypothesis search and evidence (units m, deg, chi-square units = -2 ln L).

    search_radius (m) / search_yaw_deg (deg): translation / rotation errors searched around
    the reported pose; vote_bin (m): translation vote cell; max_hypotheses: local maxima
    kept; vote_floor: share of the strongest vote a local maximum needs (weaker ones
    cannot compete and are not refined); refine_gate (m): matching gate of the
    refinement; outlier_chi2: what an unexplained box costs (a pair gains
    ``outlier_chi2 - chi2``, never less than 0); pose_slack_t (m) / pose_slack_r_deg
    (deg): std added to every pair for the residual misfit of a hypothesis; size_sigma:
    std of one box's log size (l, w, h); free_space_penalty: chi2 cost of an ego box
    inside the collaborator's observed disk that none of its boxes explains. use_*: the
    switches of the terms (module docstring).
    """

    search_radius: float = 7.0
    search_yaw_deg: float = 8.0
    vote_bin: float = 0.5
    max_hypotheses: int = 6
    vote_floor: float = 0.2
    refine_gate: float = 1.0
    outlier_chi2: float = 16.0
    pose_slack_t: float = 0.1
    pose_slack_r_deg: float = 0.3
    size_sigma: float = 0.06
    free_space_penalty: float = 2.0
    use_size: bool = True
    use_free_space: bool = True
    use_mutual_detection: bool = True

    def __post_init__(self) -> None:
        require_positive(self, _POSITIVE_FIELDS)
        if not (np.isfinite(self.free_space_penalty) and self.free_space_penalty >= 0):
            raise ValueError(
                f"free_space_penalty must be finite and >= 0; got {self.free_space_penalty}"
            )
        if not 0 <= self.vote_floor < 1:
            raise ValueError(f"vote_floor must be in [0, 1); got {self.vote_floor}")
        if int(self.max_hypotheses) < 1:
            raise ValueError(f"max_hypotheses must be an integer >= 1; got {self.max_hypotheses}")


@dataclass(frozen=True)
class BoxSet:
    """One agent's boxes in its own frame: poses (K, 3), log sizes (K, 3) (l, w, h),
    information (K, 3, 3) (box frame, as the pose graph uses it), var_t (K,) the mean of
    the centre's x and y variances (m^2), var_r (K,) the heading variance (rad^2),
    range (m): the largest distance of a box from the agent (the radius of its observed
    disk)."""

    poses: np.ndarray
    log_sizes: np.ndarray
    information: np.ndarray
    var_t: np.ndarray
    var_r: np.ndarray
    range: float


def box_set(boxes: np.ndarray, poses: np.ndarray, information: np.ndarray) -> BoxSet:
    """:class:`BoxSet` of validated boxes (K, 7) with their poses (K, 3) and information
    (K, 3, 3) from :func:`~roco_env.policies.landmarks.prepare_inputs`."""
    sizes = np.maximum(boxes[:, 3:6], 1e-3)
    # sigma_x^2 + sigma_y^2 is the trace of the xy block's inverse (rotation invariant).
    xy_cov = np.linalg.inv(information[:, :2, :2]) if boxes.shape[0] else np.zeros((0, 2, 2))
    var_t = 0.5 * (xy_cov[:, 0, 0] + xy_cov[:, 1, 1])
    distance = np.hypot(poses[:, 0], poses[:, 1])
    reach = float(distance.max()) if distance.size else 0.0
    return BoxSet(
        poses,
        np.log(sizes),
        information,
        var_t,
        1.0 / information[:, 2, 2],
        reach,
    )


def _map(pose: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Poses (K, 3) moved by the SE(2) pose (3,) (heading not wrapped: only its
    differences modulo pi are used)."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    out = np.empty_like(poses)
    out[:, 0] = c * poses[:, 0] - s * poses[:, 1] + pose[0]
    out[:, 1] = s * poses[:, 0] + c * poses[:, 1] + pose[1]
    out[:, 2] = poses[:, 2] + pose[2]
    return out


def _half_turn(angle: np.ndarray) -> np.ndarray:
    """Angle difference modulo pi, in [-pi/2, pi/2) (detected headings may be flipped)."""
    return np.mod(angle + np.pi / 2, np.pi) - np.pi / 2


def _pairs(ego: BoxSet, mapped: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """(ego index, collaborator index) of every pair of centres at most ``radius`` m apart,
    the collaborator's boxes already mapped into the ego frame (mapped (K1, 3))."""
    return close_pairs(ego.poses[:, :2], mapped[:, :2], float(radius))


def _size_chi2(ego: BoxSet, collab: BoxSet, i: np.ndarray, j: np.ndarray, p: EvidenceParams):
    """chi2 (P,) of the log-size differences of pairs (both boxes noisy: variance 2 sigma^2)."""
    diff = ego.log_sizes[i] - collab.log_sizes[j]
    return (diff * diff).sum(axis=1) / (2.0 * p.size_sigma**2)


def _vote_peak(values: np.ndarray, weight: np.ndarray, half: float, cell: float) -> float:
    """Centre of the strongest (5-cell smoothed) bin of a weighted 1D vote over [-half, half]."""
    bins = int(np.ceil(2 * half / cell))
    votes = np.bincount(
        np.minimum(((values + half) / cell).astype(np.int64), bins - 1), weight, bins
    )
    smooth = np.convolve(votes, np.ones(5), mode="same")
    return -half + (int(np.argmax(smooth)) + 0.5) * cell if smooth.max() > 0 else 0.0


def generate_hypotheses(
    ego: BoxSet, collab: BoxSet, reported: np.ndarray, p: EvidenceParams
) -> np.ndarray:
    """Initial poses (H, 3) of the strongest votes (module docstring, step 1); the first
    row is the vote maximum; empty (0, 3) when no box pair lies within the search."""
    # Rotation: heading differences (modulo pi) of nearby pairs, 0.25 deg cells.
    half = np.deg2rad(p.search_yaw_deg)
    mapped = _map(reported, collab.poses)
    i, j = _pairs(ego, mapped, p.search_radius + 2.0)
    if i.size == 0:
        return np.zeros((0, 3))
    size_weight = np.exp(-0.5 * _size_chi2(ego, collab, i, j, p)) if p.use_size else np.ones(i.size)
    dyaw = _half_turn(ego.poses[i, 2] - mapped[j, 2])
    use = np.abs(dyaw) <= half
    rotation = _vote_peak(dyaw[use], size_weight[use], half, np.deg2rad(0.25))
    rotated = reported + np.array([0.0, 0.0, rotation])
    # Translation: centre offsets on a grid of vote_bin cells, headings weighing each pair.
    mapped = _map(rotated, collab.poses)
    i, j = _pairs(ego, mapped, p.search_radius * np.sqrt(2.0))
    size_weight = np.exp(-0.5 * _size_chi2(ego, collab, i, j, p)) if p.use_size else np.ones(i.size)
    dx = ego.poses[i, 0] - mapped[j, 0]
    dy = ego.poses[i, 1] - mapped[j, 1]
    dyaw = _half_turn(ego.poses[i, 2] - mapped[j, 2])
    use = (np.abs(dx) <= p.search_radius) & (np.abs(dy) <= p.search_radius)
    weight = (size_weight * np.exp(-0.5 * (dyaw / np.deg2rad(3.0)) ** 2))[use]
    n = int(np.ceil(2 * p.search_radius / p.vote_bin))
    ix = np.minimum(((dx[use] + p.search_radius) / p.vote_bin).astype(np.int64), n - 1)
    iy = np.minimum(((dy[use] + p.search_radius) / p.vote_bin).astype(np.int64), n - 1)
    grid = np.bincount(ix * n + iy, weight, n * n).reshape(n, n)
    # 3x3 box sum: a true offset splits its votes over neighbouring cells.
    padded = np.zeros((n + 2, n + 2))  # np.pad(grid, 1) without its per-call overhead
    padded[1:-1, 1:-1] = grid
    smooth = sum(padded[a : a + n, b : b + n] for a in range(3) for b in range(3))
    peaks: list[tuple[int, int]] = []
    suppress = (1.25 / p.vote_bin) ** 2  # cells; lattice pitches (2.5 m) stay apart
    floor = max(p.vote_floor * smooth.max(), 0.0)
    for flat in np.argsort(-smooth, axis=None):
        if len(peaks) == p.max_hypotheses or smooth.flat[flat] <= floor:
            break
        a, b = divmod(int(flat), n)
        if all((a - c) ** 2 + (b - d) ** 2 > suppress for c, d in peaks):
            peaks.append((a, b))
    if not peaks:
        return np.zeros((0, 3))
    offsets = (np.array(peaks, dtype=float) + 0.5) * p.vote_bin - p.search_radius
    out = np.tile(rotated, (offsets.shape[0], 1))
    out[:, :2] += offsets
    return out


def refine_hypothesis(
    ego: BoxSet,
    collab: BoxSet,
    initial: np.ndarray,
    p: EvidenceParams,
    kernel: str | None,
    kernel_delta: float,
    min_matches: int,
) -> np.ndarray | None:
    """Up to two rounds of nearest matching within ``refine_gate`` and a robust pose solve
    (the second only when the matches changed); None when fewer than ``min_matches``
    boxes match. One compiled pass (:func:`~roco_env.policies.pose_kernels.refine_pose`)."""
    pose, ok = refine_pose(
        np.asarray(initial, dtype=float).reshape(3),
        ego.poses,
        collab.poses,
        collab.information,
        float(p.refine_gate),
        KERNEL_CODES[kernel],
        float(kernel_delta),
        int(min_matches),
        _REFINE_ITERATIONS,
        _REFINE_TOLERANCE,
        _MIN_DIAG,
    )
    return pose if ok else None


def _best_gains(
    ego: BoxSet, collab: BoxSet, pose: np.ndarray, p: EvidenceParams
) -> tuple[np.ndarray, np.ndarray]:
    """Per box, the largest gain ``outlier_chi2 - chi2 > 0`` of its pairs under ``pose``
    (0 for a box no pair explains): (collaborator boxes (K1,), ego boxes (K0,)); chi2
    from position, heading modulo pi and (when used) log sizes, both boxes' variances and
    the pose slack (:func:`~roco_env.policies.matching_kernels.best_pair_gains`)."""
    return best_pair_gains(
        ego.poses,
        ego.log_sizes,
        ego.var_t,
        ego.var_r,
        _map(pose, collab.poses),
        collab.log_sizes,
        collab.var_t,
        collab.var_r,
        p.pose_slack_t**2,
        np.deg2rad(p.pose_slack_r_deg) ** 2,
        2.0 * p.size_sigma**2 if p.use_size else 0.0,
        float(p.outlier_chi2),
    )


def score_hypotheses(
    ego: BoxSet, collab: BoxSet, poses: np.ndarray, p: EvidenceParams
) -> np.ndarray:
    """Evidence (H,) of each hypothesis pose (H, 3), in chi2 units (module docstring, step 3;
    priors not included)."""
    # Only boxes inside the other agent's observed disk under *every* hypothesis count:
    # otherwise a hypothesis that pulls more boxes into the overlap scores higher.
    forward_set = np.ones(collab.poses.shape[0], dtype=bool)
    backward_set = np.ones(ego.poses.shape[0], dtype=bool)
    for pose in poses:
        mapped = _map(pose, collab.poses)
        forward_set &= np.hypot(mapped[:, 0], mapped[:, 1]) <= ego.range
        backward_set &= np.hypot(*(ego.poses[:, :2] - pose[:2]).T) <= collab.range
    scores = np.zeros(poses.shape[0])
    for h, pose in enumerate(poses):
        forward, backward = _best_gains(ego, collab, pose, p)
        scores[h] = float(forward[forward_set].sum())
        if p.use_free_space:
            scores[h] += float(backward[backward_set].sum())
            unexplained = backward_set & (backward == 0)
            scores[h] -= p.free_space_penalty * float(np.count_nonzero(unexplained))
        if p.use_mutual_detection:
            scores[h] += _mutual_detection(ego, collab, pose, backward == 0, forward == 0, p)
    return scores


def _mutual_detection(
    ego: BoxSet,
    collab: BoxSet,
    pose: np.ndarray,
    ego_unexplained: np.ndarray,
    collab_unexplained: np.ndarray,
    p: EvidenceParams,
) -> float:
    """Gain of the two direct detections the hypothesis predicts: an ego box where it puts
    the collaborator's vehicle (pose ``pose``, heading modulo pi) that no collaborator box
    explains (nobody detects itself), and a collaborator box where it puts the ego."""
    total = 0.0
    c, s = np.cos(pose[2]), np.sin(pose[2])
    inverse = np.array([-c * pose[0] - s * pose[1], s * pose[0] - c * pose[1], -pose[2]])
    slack_t, slack_r = p.pose_slack_t**2, np.deg2rad(p.pose_slack_r_deg) ** 2
    for boxes, target, unexplained in (
        (ego, pose, ego_unexplained),
        (collab, inverse, collab_unexplained),
    ):
        if boxes.poses.shape[0] == 0:
            continue
        d = boxes.poses[:, :2] - target[:2]
        dyaw = _half_turn(boxes.poses[:, 2] - target[2])
        chi2 = (d * d).sum(axis=1) / (boxes.var_t + slack_t) + dyaw * dyaw / (boxes.var_r + slack_r)
        gains = np.where(unexplained, np.maximum(p.outlier_chi2 - chi2, 0.0), 0.0)
        total += float(gains.max())
    return total


def pose_distance(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(translation m, |yaw| rad) between two poses (3,)."""
    # Scalar math: the same hypot and floor-modulo wrap as np.hypot / geometry.wrap_angle.
    yaw = (float(a[2]) - float(b[2]) + math.pi) % (2.0 * math.pi) - math.pi
    return math.hypot(a[0] - b[0], a[1] - b[1]), abs(yaw)
