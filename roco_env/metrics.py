"""Detection and alignment metrics: the OpenCOOD/CoAlign AP protocol, RPE, success rate,
matching precision/recall.

AP protocol (docs/metrics.md), on BEV footprints of boxes (x, y, z, l, w, h, yaw):

* Per frame, predictions are visited by descending score (stable: ties keep
  input order). Each takes the *remaining* ground-truth box with maximum BEV IoU
  (ties: the lowest GT index); it is a true positive if that IoU is >= the
  threshold (the GT box is then removed), otherwise a false positive. The frame's
  GT count is accumulated even when it has no predictions.
* Dataset AP: every frame's (score, tp, fp) is sorted globally by descending
  score (stable: ties keep the order frames were added, then in-frame order);
  cumulative precision tp / (tp + fp) and recall tp / n_gt; VOC all-point
  interpolation: recall padded with 0 and 1, precision with 0 and 0, precision
  made monotone from the right, AP = sum of delta-recall x precision.

Edge cases (decided here; OpenCOOD divides by zero): no GT and no predictions
-> NaN (nothing to evaluate); GT but no predictions -> 0.0 (recall is 0);
predictions but no GT -> 0.0 (every prediction is a false positive). IoU
thresholds must lie in (0, 1]: a prediction never matches a GT it does not overlap.

``frame_stats`` / ``APAccumulator.add_frame`` match one frame;
``match_frames`` (what the env does for all its egos each step) and
``APAccumulator.add_frames`` match many frames in one vectorised pass with
identical results: one candidate search and one exact-IoU call for all frames;
predictions overlapping no GT are false positives without further work, and
the sequential greedy pass visits only the predictions competing for a GT.

Relative pose errors are in metres and degrees.

Matching precision/recall of an alignment result against true object identities
(box pairs are unordered; a "box" is (slot, box index), slot -1 = ego):

* precision = share of the reported ``matched_pairs`` whose two boxes carry the same
  true object id (>= 0); NaN when nothing was reported;
* recall = share of the true cross-agent correspondences that were reported. A true
  correspondence is a pair of boxes of *different* agents with the same id >= 0:
  ego <-> collaborator pairs, and collaborator <-> collaborator pairs when
  ``include_collab_pairs`` (the default: both built-in aligners report those);
  NaN when there is none.

Ids of -1 mean false positive or padding; pass masks too if padding carries other ids.
"""

from __future__ import annotations

import itertools
import operator
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from roco_env.geometry import (
    _pair_iou,
    validate_boxes,
    wrap_angle,
)

if TYPE_CHECKING:
    from roco_env.policies.base import AlignmentResult

__all__ = [
    "DEFAULT_IOU_THRESHOLDS",
    "FrameStats",
    "frame_stats",
    "match_frames",
    "frame_ap",
    "average_precision",
    "average_precisions",
    "APAccumulator",
    "in_range_mask",
    "relative_pose_error",
    "success_rate",
    "HARM_MARGIN",
    "harm_share",
    "matching_precision_recall",
]

DEFAULT_IOU_THRESHOLDS: tuple[float, ...] = (0.3, 0.5, 0.7)

# Up to this many (prediction, GT) pairs, a dense centre-distance test finds the
# candidate pairs faster than building KD-trees (the crossover: docs/performance.md).
_DENSE_MAX_PAIRS = 10_000


def _thresholds(iou_thresholds: Sequence[float]) -> tuple[float, ...]:
    try:
        values = tuple(float(t) for t in iou_thresholds)
    except (TypeError, ValueError):
        values = ()
    if not values or not all(0.0 < t <= 1.0 for t in values):
        raise ValueError(
            f"iou_thresholds must be a non-empty sequence of values in (0, 1]; got {iou_thresholds}"
        )
    if len(set(values)) != len(values):
        raise ValueError(f"iou_thresholds must not repeat values; got {iou_thresholds}")
    return values


def _scores(scores: np.ndarray, n_boxes: int, name: str) -> np.ndarray:
    arr = np.asarray(scores, dtype=float).reshape(-1)
    if arr.shape[0] != n_boxes:
        raise ValueError(f"{name} must have one entry per box ({n_boxes}); got {arr.shape[0]}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} contains NaN or inf; all values must be finite")
    return arr


@dataclass(frozen=True)
class FrameStats:
    """One frame's matching result, the exact input of :meth:`APAccumulator.add_stats`.

    scores (P,) prediction scores sorted descending; tp, fp (T, P) bool, one row
    per IoU threshold in ``thresholds`` (T of them); n_gt the frame's GT count.
    """

    scores: np.ndarray
    tp: np.ndarray
    fp: np.ndarray
    n_gt: int
    thresholds: tuple[float, ...] = DEFAULT_IOU_THRESHOLDS

    def __post_init__(self) -> None:
        scores = np.asarray(self.scores, dtype=float).reshape(-1)
        thresholds = _thresholds(self.thresholds)
        shape = (len(thresholds), scores.shape[0])
        tp, fp = (np.asarray(flags, dtype=bool) for flags in (self.tp, self.fp))
        if tp.size != scores.size * len(thresholds) or fp.size != tp.size:
            raise ValueError(
                f"tp and fp must have shape (thresholds, predictions) = {shape}; "
                f"got {tp.shape} and {fp.shape}"
            )
        tp, fp = tp.reshape(shape), fp.reshape(shape)
        if (tp == fp).any():
            raise ValueError("tp and fp must be complementary: each prediction is exactly one")
        if not np.isfinite(scores).all():
            raise ValueError("scores contains NaN or inf; all values must be finite")
        if int(self.n_gt) != self.n_gt or self.n_gt < 0:
            raise ValueError(f"n_gt must be a non-negative integer; got {self.n_gt}")
        if (tp.sum(axis=1) > self.n_gt).any():
            raise ValueError(f"tp counts exceed n_gt ({self.n_gt})")
        object.__setattr__(self, "scores", scores)
        object.__setattr__(self, "tp", tp)
        object.__setattr__(self, "fp", fp)
        object.__setattr__(self, "n_gt", int(self.n_gt))
        object.__setattr__(self, "thresholds", thresholds)

    @classmethod
    def _trusted(cls, scores: np.ndarray, tp: np.ndarray, n_gt: int,
                 thresholds: tuple[float, ...]) -> FrameStats:
        """Stats from the matcher, already valid by construction: skips __post_init__."""
        stats = object.__new__(cls)
        for name, value in (("scores", scores), ("tp", tp), ("fp", ~tp), ("n_gt", n_gt),
                            ("thresholds", thresholds)):
            object.__setattr__(stats, name, value)
        return stats


def frame_stats(
    pred_boxes: np.ndarray,
    pred_scores: np.ndarray,
    gt_boxes: np.ndarray,
    iou_thresholds: Sequence[float] = DEFAULT_IOU_THRESHOLDS,
) -> FrameStats:
    """Greedy OpenCOOD matching of one frame's predictions (P, 7) against GT (G, 7).

    Boxes must be in the same frame. Returns scores sorted descending and the
    tp/fp flags in that order, one row per threshold.
    """
    thresholds = _thresholds(iou_thresholds)
    return _frames_stats([_validated_frame(pred_boxes, pred_scores, gt_boxes, "")], thresholds)[0]


LabelledFrame = tuple[np.ndarray, np.ndarray, np.ndarray]  # pred boxes (P, 7), scores (P,), GT (G, 7)


def match_frames(frames: Sequence[LabelledFrame],
                 iou_thresholds: Sequence[float] = DEFAULT_IOU_THRESHOLDS) -> list[FrameStats]:
    """:func:`frame_stats` of many frames ``(pred_boxes, pred_scores, gt_boxes)`` at once.

    Each frame's boxes share one frame of reference (frames may differ, e.g. one
    per ego). Same results as calling :func:`frame_stats` on each frame.
    """
    thresholds = _thresholds(iou_thresholds)
    return _frames_stats(_validated_frames(frames), thresholds)


def _validated_frames(frames: Sequence[LabelledFrame]) -> list[LabelledFrame]:
    """Frames with validated arrays; errors name the frame (``frames[k].pred_scores``)."""
    checked = []
    for k, frame in enumerate(frames):
        if len(frame) != 3:
            raise ValueError(
                f"frames[{k}] must be (pred_boxes, pred_scores, gt_boxes); got {len(frame)} items"
            )
        checked.append(_validated_frame(*frame, f"frames[{k}]."))
    return checked


def _validated_frame(pred_boxes: np.ndarray, pred_scores: np.ndarray, gt_boxes: np.ndarray,
                     prefix: str) -> LabelledFrame:
    pred_boxes = validate_boxes(pred_boxes, f"{prefix}pred_boxes")
    return (
        pred_boxes,
        _scores(pred_scores, pred_boxes.shape[0], f"{prefix}pred_scores"),
        validate_boxes(gt_boxes, f"{prefix}gt_boxes"),
    )


def _frames_stats(frames: Sequence[LabelledFrame], thresholds: tuple[float, ...]) -> list[FrameStats]:
    """FrameStats of validated frames, matched in one pass."""
    if not frames:
        return []
    scores, tp, start = _match_frames(frames, np.asarray(thresholds))
    return [FrameStats._trusted(scores[lo:hi], tp[:, lo:hi], frame[2].shape[0], thresholds)
            for frame, lo, hi in zip(frames, start[:-1], start[1:], strict=True)]


def _match_frames(frames: Sequence[LabelledFrame],
                  thresholds: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """Greedy matching of validated frames, all at once.

    Returns the predictions' scores (P,) frame by frame, each frame sorted by
    descending score (stable), their tp flags (T, P) and the frames' start
    offsets into them (F + 1 ints).
    """
    n_pred = [len(frame[1]) for frame in frames]
    pred_frame = np.repeat(np.arange(len(frames)), n_pred)
    gt_frame = np.repeat(np.arange(len(frames)), [len(frame[2]) for frame in frames])
    scores = np.concatenate([frame[1] for frame in frames])
    order = np.lexsort((-scores, pred_frame))
    preds = np.concatenate([frame[0] for frame in frames])[order]
    gts = np.concatenate([frame[2] for frame in frames])
    rows, cols, iou = _overlapping_pairs(preds, gts,
                                         *_candidate_pairs(preds, gts, pred_frame, gt_frame))
    tp = _greedy_match(rows, cols, iou, scores.size, gts.shape[0], thresholds)
    return scores[order], tp, list(itertools.accumulate(n_pred, initial=0))


def _overlapping_pairs(preds: np.ndarray, gts: np.ndarray, rows: np.ndarray,
                       cols: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The candidate pairs (rows, cols) with IoU > 0, and their IoUs.

    Boxes are validated already, so the exact IoU is called directly (and not
    at all without candidates, e.g. for an empty frame).
    """
    if rows.size == 0:
        return rows, cols, np.zeros(0)
    iou = _pair_iou(preds[rows], gts[cols])
    overlap = np.flatnonzero(iou > 0.0)
    return rows[overlap], cols[overlap], iou[overlap]


def _candidate_pairs(preds: np.ndarray, gts: np.ndarray, pred_frame: np.ndarray,
                     gt_frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(prediction, GT) index pairs of the same frame that may overlap, sorted by row then column.

    A superset of the pairs with IoU > 0: the circumscribed circles overlap
    (strictly), the test of ``geometry.bev_candidate_pairs``. Small inputs test
    all pairs densely; larger ones get neighbours from scipy KD-trees (frames
    kept apart on a third axis, farther than the search radius) instead of all
    same-frame pairs: O(n log n), not P x G.
    """
    empty = np.zeros(0, dtype=np.int64)
    if preds.shape[0] == 0 or gts.shape[0] == 0:
        return empty, empty
    radius_pred = 0.5 * np.hypot(preds[:, 3], preds[:, 4])
    radius_gt = 0.5 * np.hypot(gts[:, 3], gts[:, 4])
    if preds.shape[0] * gts.shape[0] <= _DENSE_MAX_PAIRS:
        return _dense_candidate_pairs(preds, gts, radius_pred, radius_gt, pred_frame, gt_frame)
    reach = radius_pred.max() + radius_gt.max()
    spacing = 4.0 * reach + 1.0
    pairs = cKDTree(np.column_stack([preds[:, :2], pred_frame * spacing])).sparse_distance_matrix(
        cKDTree(np.column_stack([gts[:, :2], gt_frame * spacing])), reach, output_type="ndarray")
    rows, cols = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
    near = (np.square(preds[rows, 0] - gts[cols, 0]) + np.square(preds[rows, 1] - gts[cols, 1])
            < np.square(radius_pred[rows] + radius_gt[cols]))
    rows, cols = rows[near], cols[near]
    order = np.lexsort((cols, rows))
    return rows[order], cols[order]


def _dense_candidate_pairs(preds: np.ndarray, gts: np.ndarray, radius_pred: np.ndarray,
                           radius_gt: np.ndarray, pred_frame: np.ndarray,
                           gt_frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_candidate_pairs` by testing every (prediction, GT) pair; row-major order."""
    gap = np.square(preds[:, None, 0] - gts[None, :, 0])
    gap += np.square(preds[:, None, 1] - gts[None, :, 1])
    near = gap < np.square(radius_pred[:, None] + radius_gt[None, :])
    if not pred_frame[0] == pred_frame[-1] == gt_frame[0] == gt_frame[-1]:  # several frames
        near &= pred_frame[:, None] == gt_frame[None, :]
    return np.nonzero(near)


def _greedy_match(rows: np.ndarray, cols: np.ndarray, iou: np.ndarray, n_pred: int,
                  n_gt: int, thresholds: np.ndarray) -> np.ndarray:
    """TP flags (T, P) from the overlapping (prediction, GT) pairs, IoU > 0.

    ``rows`` index predictions in matching order (descending score within each
    frame), pairs sorted by row then column. Thresholds are > 0, so a GT only
    matters to the predictions overlapping it: a prediction sharing none of its
    GTs with another one simply takes its best GT; only predictions competing
    for a GT need the sequential greedy pass (each match removes its GT).
    """
    if rows.size == 0:
        return np.zeros((thresholds.size, n_pred), dtype=bool)
    best = np.zeros(n_pred)
    np.maximum.at(best, rows, iou)
    tp = best[None, :] >= thresholds[:, None]
    shared = np.bincount(cols, minlength=n_gt) > 1
    competing = np.zeros(n_pred, dtype=bool)
    competing[rows[shared[cols]]] = True
    pairs = competing[rows]
    taken: list[set[int]] = [set() for _ in thresholds]
    # Plain Python: a few pairs per competing prediction, where numpy calls cost more.
    for rank, candidates in itertools.groupby(
        zip(rows[pairs].tolist(), cols[pairs].tolist(), iou[pairs].tolist(), strict=True),
        key=operator.itemgetter(0),
    ):
        candidates = list(candidates)
        for k, thr in enumerate(thresholds.tolist()):
            best_iou, best_gt = 0.0, -1
            for _, gt, value in candidates:  # first of equal IoUs, like argmax
                if value > best_iou and gt not in taken[k]:
                    best_iou, best_gt = value, gt
            tp[k, rank] = best_iou >= thr
            if tp[k, rank]:
                taken[k].add(best_gt)
    return tp


def average_precision(scores: np.ndarray, tp: np.ndarray, n_gt: int) -> float:
    """VOC all-point AP of pooled predictions: scores (P,), tp (P,) bool, n_gt GT boxes.

    Applies the NaN/0 edge-case rules of the module docstring.
    """
    tp = np.asarray(tp, dtype=bool).reshape(1, -1)
    return float(average_precisions(scores, tp, n_gt)[0])


def average_precisions(scores: np.ndarray, tp: np.ndarray, n_gt: int) -> np.ndarray:
    """:func:`average_precision` of each row of tp (T, P) bool, all rows at once -> (T,).

    scores (P,) is shared by the rows (one row per IoU threshold).
    """
    scores = np.asarray(scores, dtype=float).reshape(-1)
    tp = np.asarray(tp, dtype=bool)
    if tp.ndim != 2 or tp.shape[1] != scores.shape[0]:
        raise ValueError(f"tp must have shape (thresholds, {scores.shape[0]}) for "
                         f"{scores.shape[0]} scores; got {tp.shape}")
    if n_gt == 0:
        return np.full(tp.shape[0], np.nan if scores.size == 0 else 0.0)
    if scores.size == 0:
        return np.zeros(tp.shape[0])
    tp_cum = np.cumsum(tp[:, np.argsort(-scores, kind="stable")], axis=1)
    rows = tp.shape[0]
    recall = np.concatenate([np.zeros((rows, 1)), tp_cum / n_gt, np.ones((rows, 1))], axis=1)
    precision = np.concatenate([np.zeros((rows, 1)), tp_cum / np.arange(1, scores.size + 1),
                                np.zeros((rows, 1))], axis=1)
    precision = np.maximum.accumulate(precision[:, ::-1], axis=1)[:, ::-1]
    return np.sum(np.diff(recall, axis=1) * precision[:, 1:], axis=1)


def frame_ap(
    pred_boxes: np.ndarray,
    pred_scores: np.ndarray,
    gt_boxes: np.ndarray,
    iou_thresholds: Sequence[float] = DEFAULT_IOU_THRESHOLDS,
) -> dict[float, float]:
    """AP of a single frame per threshold (NaN when it has no GT and no predictions)."""
    acc = APAccumulator(iou_thresholds)
    acc.add_frame(pred_boxes, pred_scores, gt_boxes)
    return acc.ap()


class APAccumulator:
    """Pools frames and computes dataset AP per IoU threshold (OpenCOOD protocol)."""

    def __init__(self, iou_thresholds: Sequence[float] = DEFAULT_IOU_THRESHOLDS) -> None:
        self.thresholds = _thresholds(iou_thresholds)
        self._scores: list[np.ndarray] = []
        self._tp: list[np.ndarray] = []
        self._n_gt = 0

    @property
    def n_frames(self) -> int:
        return len(self._scores)

    @property
    def n_gt(self) -> int:
        return self._n_gt

    def add_frame(self, pred_boxes: np.ndarray, pred_scores: np.ndarray,
                  gt_boxes: np.ndarray) -> FrameStats:
        """Match one frame (boxes in one common frame) and pool it; returns its stats."""
        frame = _validated_frame(pred_boxes, pred_scores, gt_boxes, "")
        stats = _frames_stats([frame], self.thresholds)[0]
        self._pool(stats)
        return stats

    def add_frames(self, frames: Sequence[LabelledFrame]) -> None:
        """Match and pool many frames ``(pred_boxes, pred_scores, gt_boxes)`` in one go.

        Same result as calling :meth:`add_frame` on each, vectorised across frames.
        """
        for stats in _frames_stats(_validated_frames(frames), self.thresholds):
            self._pool(stats)

    def add_stats(self, stats: FrameStats) -> None:
        """Pool an already matched frame (e.g. the env's frame_scores/tp/fp/n_gt info)."""
        if not isinstance(stats, FrameStats):
            raise ValueError(f"stats must be a FrameStats; got {type(stats).__name__}")
        if stats.thresholds != self.thresholds:
            raise ValueError(
                f"stats.thresholds must equal the accumulator's {self.thresholds}; "
                f"got {stats.thresholds}"
            )
        self._pool(stats)

    def _pool(self, stats: FrameStats) -> None:
        """Append checked stats; ap() concatenates them lazily."""
        self._scores.append(stats.scores)
        self._tp.append(stats.tp)
        self._n_gt += stats.n_gt

    def ap(self) -> dict[float, float]:
        """Dataset AP per threshold, ``{0.3: .., 0.5: .., 0.7: ..}``."""
        scores = np.concatenate(self._scores) if self._scores else np.zeros(0)
        tp = (
            np.concatenate(self._tp, axis=1)
            if self._tp
            else np.zeros((len(self.thresholds), 0), dtype=bool)
        )
        return dict(zip(self.thresholds, average_precisions(scores, tp, self._n_gt).tolist(),
                        strict=True))


def _range(values: Sequence[float], name: str) -> tuple[float, float]:
    arr = np.asarray(values, dtype=float).reshape(-1)
    if arr.shape != (2,) or not np.all(np.isfinite(arr)) or arr[0] >= arr[1]:
        raise ValueError(f"{name} must be two finite values [low, high] with low < high; got {values}")
    return float(arr[0]), float(arr[1])


def in_range_mask(boxes: np.ndarray, x_range: Sequence[float],
                  y_range: Sequence[float]) -> np.ndarray:
    """(N,) bool: True where all four BEV corners of a box lie inside the ranges (inclusive).

    ``boxes`` (N, 7) and the ranges (metres) are in the same (ego) frame.
    """
    boxes = validate_boxes(boxes, "boxes")
    (x_lo, x_hi), (y_lo, y_hi) = _range(x_range, "x_range"), _range(y_range, "y_range")
    # The corners' extreme coordinates: centre +- the half extents of the rotated footprint.
    cos, sin = np.abs(np.cos(boxes[:, 6])), np.abs(np.sin(boxes[:, 6]))
    half_x = 0.5 * (cos * boxes[:, 3] + sin * boxes[:, 4])
    half_y = 0.5 * (sin * boxes[:, 3] + cos * boxes[:, 4])
    return ((boxes[:, 0] - half_x >= x_lo) & (boxes[:, 0] + half_x <= x_hi)
            & (boxes[:, 1] - half_y >= y_lo) & (boxes[:, 1] + half_y <= y_hi))


def _poses_allow_nan(poses: np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(poses, dtype=float)
    if arr.ndim == 1 and arr.size == 0:
        arr = arr.reshape(0, 3)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3) = (x, y, yaw); got {arr.shape}")
    if np.any(np.isinf(arr)):
        raise ValueError(f"{name} contains inf; values must be finite (NaN marks an empty slot)")
    return arr


def relative_pose_error(estimated: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Errors (N, 2) = [translation m, rotation deg] of estimated vs true poses (N, 3).

    Translation error is the Euclidean distance of the translations (equal to the
    norm of the translation of ``truth^-1 * estimated``); rotation error is the
    absolute wrapped yaw difference in degrees. Rows containing NaN (empty
    slots) give NaN rows.
    """
    estimated = _poses_allow_nan(estimated, "estimated")
    truth = _poses_allow_nan(truth, "truth")
    if estimated.shape != truth.shape:
        raise ValueError(
            f"estimated and truth must have the same shape; got {estimated.shape} and {truth.shape}"
        )
    trans = np.hypot(estimated[:, 0] - truth[:, 0], estimated[:, 1] - truth[:, 1])
    rot = np.degrees(np.abs(wrap_angle(estimated[:, 2] - truth[:, 2])))
    errors = np.stack([trans, rot], axis=1)
    errors[np.isnan(errors).any(axis=1)] = np.nan
    return errors


def success_rate(errors: np.ndarray, lam: float) -> float:
    """Share of rows with translation < lam m AND rotation < lam deg; NaN rows ignored.

    ``errors`` (N, 2) as returned by :func:`relative_pose_error`. NaN if no row is valid.
    """
    arr = np.asarray(errors, dtype=float)
    if arr.ndim == 1 and arr.size == 0:
        arr = arr.reshape(0, 2)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"errors must have shape (N, 2) = (translation m, rotation deg); got {arr.shape}")
    if np.any(arr < 0):
        raise ValueError("errors must be non-negative (or NaN for empty slots)")
    if not (np.isfinite(lam) and lam > 0):
        raise ValueError(f"lam must be a finite positive number (m and deg); got {lam}")
    valid = arr[~np.isnan(arr).any(axis=1)]
    if valid.shape[0] == 0:
        return float("nan")
    return float(np.mean((valid[:, 0] < lam) & (valid[:, 1] < lam)))


# m: a pose counts as made worse than reported (harmed) when its translation error grew by
# more than this (the stress search's ``harm``, roco_antialias's lattice benchmark).
HARM_MARGIN = 0.5


def harm_share(before: np.ndarray, after: np.ndarray, margin: float = HARM_MARGIN) -> float:
    """Share of rows whose translation error (m, column 0 of errors (N, 2) as returned by
    :func:`relative_pose_error`) grew by more than ``margin`` m from ``before`` (the
    reported poses') to ``after`` (the corrected ones'); NaN without rows."""
    before, after = np.reshape(before, (-1, 2)), np.reshape(after, (-1, 2))
    if before.shape != after.shape:
        raise ValueError(f"before/after shapes differ: {before.shape} vs {after.shape}")
    if before.shape[0] == 0:
        return float("nan")
    return float(np.mean(after[:, 0] > before[:, 0] + margin))


def _id_table(ego_ids: np.ndarray, collab_ids: np.ndarray) -> np.ndarray:
    """ids (N + 1, K): row 0 the ego, row j + 1 collaborator slot j."""
    k = max(ego_ids.size, collab_ids.shape[1])
    table = np.full((collab_ids.shape[0] + 1, k), -1, dtype=np.int64)
    table[0, : ego_ids.size] = ego_ids
    table[1:, : collab_ids.shape[1]] = collab_ids
    return table


def matching_precision_recall(
    result: AlignmentResult,
    ego_ids: np.ndarray,
    collab_ids: np.ndarray,
    ego_mask: np.ndarray | None = None,
    collab_mask: np.ndarray | None = None,
    include_collab_pairs: bool = True,
) -> tuple[float, float]:
    """(precision, recall) of ``result.matched_pairs`` (slot_a, box_a, slot_b, box_b).

    ego_ids (K,), collab_ids (N, K): true object id per observation position (-1 = none);
    optional masks (K,), (N, K) mark the used positions (others count as -1).
    """
    ego_ids = np.asarray(ego_ids, dtype=np.int64).reshape(-1).copy()
    collab_ids = np.asarray(collab_ids, dtype=np.int64)
    collab_ids = collab_ids.reshape(collab_ids.shape[0] if collab_ids.size else 0, -1).copy()
    if ego_mask is not None:
        ego_ids[~np.asarray(ego_mask, dtype=bool)] = -1
    if collab_mask is not None:
        collab_ids[~np.asarray(collab_mask, dtype=bool)] = -1
    table = _id_table(ego_ids, collab_ids)
    pairs = np.asarray(result.matched_pairs, dtype=np.int64).reshape(-1, 4)
    if pairs.size and (
        pairs[:, [0, 2]].max() >= collab_ids.shape[0]
        or pairs[:, [0, 2]].min() < -1
        or pairs[:, [1, 3]].min() < 0
        or pairs[:, [1, 3]].max() >= table.shape[1]
    ):
        raise ValueError("result.matched_pairs refers to slots or boxes outside ego_ids/collab_ids")
    if not include_collab_pairs:
        pairs = pairs[(pairs[:, 0] == -1) | (pairs[:, 2] == -1)]
    id_a = table[pairs[:, 0] + 1, pairs[:, 1]]
    id_b = table[pairs[:, 2] + 1, pairs[:, 3]]
    correct = (id_a == id_b) & (id_a >= 0)
    precision = float(correct.mean()) if pairs.size else float("nan")
    truth = _true_pairs(table, include_collab_pairs)
    found = {_key(p) for p in pairs[correct]}
    recall = len(truth & found) / len(truth) if truth else float("nan")
    return precision, recall


def _key(pair: np.ndarray) -> tuple[int, int, int, int]:
    a, b = (int(pair[0]), int(pair[1])), (int(pair[2]), int(pair[3]))
    return (*min(a, b), *max(a, b))


def _true_pairs(table: np.ndarray, include_collab_pairs: bool) -> set[tuple[int, int, int, int]]:
    """All unordered cross-agent box pairs with the same id >= 0, as (slot, box, slot, box)."""
    slot, box = np.nonzero(table >= 0)
    ids = table[slot, box]
    first, second = np.nonzero((ids[:, None] == ids[None, :]) & (slot[:, None] < slot[None, :]))
    keep = (slot[first] == 0) | include_collab_pairs
    first, second = first[keep], second[keep]
    return {
        (int(slot[a]) - 1, int(box[a]), int(slot[b]) - 1, int(box[b]))
        for a, b in zip(first, second, strict=True)
    }
