"""Per-ego evaluation of one step: ground truth, fused-detection AP, RPE, reward, info.

Frames: everything here is in the ego's TRUE frame. The ego's own boxes are
already there (sensors see the world correctly, docs/conventions.md); the
collaborators' boxes got there through the corrected relative poses, so a
wrong correction shows up as misplaced boxes. Ground truth for ego i
(``evaluation.ground_truth``, docs/metrics.md): ``visible`` (default) = the
objects visible to at least one agent of i's collaboration (i and its
collaborator slots; with the network stage on, the agents in its communication range
now, whether their messages arrived or not), minus i's own vehicle, kept only when all BEV corners lie
inside the evaluation range; ``opencood`` = OpenCOOD's convention: every
object of the world state (i's own vehicle included, no occlusion filter) whose
BEV corners lie inside the range and whose bottom and top lie inside
``z_range`` in i's LiDAR frame. Fused predictions are range filtered in BEV
either way (OpenCOOD filters predictions before matching too).
Relative pose errors are [translation m, rotation deg].
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import ClassVar, Protocol

import numpy as np

from roco_env.fusion import FusedDetections
from roco_env.geometry import se2_inverse, transform_boxes
from roco_env.metrics import (
    DEFAULT_IOU_THRESHOLDS,
    FrameStats,
    average_precisions,
    in_range_mask,
    match_frames,
    relative_pose_error,
)
from roco_env.observation import EgoView
from roco_env.scenario import GROUND_TRUTHS, EvaluationConfig
from roco_env.stages import stage
from roco_env.traffic.state import WorldState

AP_KEYS: dict[float, str] = {0.3: "ap30", 0.5: "ap50", 0.7: "ap70"}


@dataclass(frozen=True)
class EgoEvaluation:
    """One ego's evaluated frame.

    gt_boxes (G, 7); pred_boxes (P, 7) / pred_scores (P,) the fused,
    range-filtered detections (descending score); stats: the frame's matching
    (AP input); ap: threshold -> per-step AP (NaN with no GT and no
    predictions); rpe_before / rpe_after (N, 2) errors of the reported /
    corrected T_{j->i}, NaN rows for empty slots.
    """

    gt_boxes: np.ndarray
    pred_boxes: np.ndarray
    pred_scores: np.ndarray
    stats: FrameStats
    ap: dict[float, float]
    rpe_before: np.ndarray
    rpe_after: np.ndarray


def ground_truths(state: WorldState, visible: np.ndarray,
                  egos: Sequence[tuple[int, Sequence[int]]], x_range: Sequence[float],
                  y_range: Sequence[float], convention: str = "visible",
                  z_range: Sequence[float] = (-3.0, 1.0)) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per (ego, collaborators): GT boxes (G, 7) in the ego's true frame and object ids (G,).

    visible (A, M) bool: which agent sees which object (state's object order).
    convention: ``visible`` or ``opencood`` (module docstring); z_range (m, ego LiDAR
    frame: heights above the ego's sensor) applies to ``opencood`` only.
    All egos are transformed and range-tested in one batch.
    """
    if convention not in GROUND_TRUTHS:
        raise ValueError(f"evaluation.ground_truth must be one of {list(GROUND_TRUTHS)}; "
                         f"got {convention!r}")
    ego_rows = np.array([ego for ego, _ in egos], dtype=np.int64)
    if convention == "visible":
        visible = np.asarray(visible, dtype=bool)
        rows = [np.flatnonzero(visible[[ego, *collaborators]].any(axis=0)
                               & (state.object_ids != state.agent_object_ids[ego]))
                for ego, collaborators in egos]
    else:
        rows = [np.arange(state.num_objects)] * len(egos)
    counts = [r.shape[0] for r in rows]
    objects = np.concatenate([np.zeros(0, dtype=np.int64), *rows])
    to_ego = np.repeat(se2_inverse(state.agent_poses[ego_rows]).reshape(-1, 3), counts, axis=0)
    boxes = transform_boxes(state.object_boxes[objects], to_ego)
    keep = in_range_mask(boxes, x_range, y_range)
    if convention == "opencood":
        sensor_z = np.repeat(state.ground_heights[ego_rows] + state.sensor_heights[ego_rows],
                             counts)
        keep &= in_z_range(boxes, sensor_z, z_range)
    return [(b[k], state.object_ids[o][k]) for b, k, o in zip(
        _split(boxes, counts), _split(keep, counts), rows, strict=True)]


def in_z_range(boxes: np.ndarray, sensor_z: np.ndarray, z_range: Sequence[float]) -> np.ndarray:
    """(N,) bool: True where box bottom and top (world z of boxes (N, 7), m) lie inside
    ``z_range`` [low, high] (inclusive) measured from ``sensor_z`` (N,) (each box's ego
    LiDAR height, world z): OpenCOOD's test that all 8 corners are in its z range."""
    low, high = float(z_range[0]), float(z_range[1])
    z = boxes[:, 2] - sensor_z
    return (z - boxes[:, 5] / 2 >= low) & (z + boxes[:, 5] / 2 <= high)


def ground_truth(state: WorldState, visible: np.ndarray, ego: int, collaborators: Sequence[int],
                 x_range: Sequence[float], y_range: Sequence[float], convention: str = "visible",
                 z_range: Sequence[float] = (-3.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """GT boxes (G, 7) in ego ``ego``'s true frame and their object ids (G,) (one ego)."""
    return ground_truths(state, visible, [(ego, collaborators)], x_range, y_range, convention,
                         z_range)[0]


def truth_collaborators(view: EgoView) -> tuple[int, ...]:
    """The agents whose sight makes ``view``'s ego's ``visible`` ground truth besides its own:
    its collaborator slots, or with the network stage on the agents it would hear now over
    an instant, lossless link (a late or lost message costs what only they see)."""
    return view.collaborators if view.in_range is None else view.in_range


def slot_errors(views: Sequence[EgoView], corrected: Sequence[np.ndarray],
                max_collaborators: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per view: RPE (N, 2) of the reported and of the corrected T_{j->i}, NaN rows for empty slots.

    corrected[k] (n_k, 3): the corrected poses of view k's filled slots.
    """
    counts = [len(view.collaborators) for view in views]
    truth = np.concatenate([np.zeros((0, 3)), *(v.true_relative for v in views)])
    reported = np.concatenate([np.zeros((0, 3)), *(v.reported_relative for v in views)])
    fixed = np.concatenate([np.zeros((0, 3)), *corrected])
    out = []
    for errors_before, errors_after in zip(
            _split(relative_pose_error(reported, truth), counts),
            _split(relative_pose_error(fixed, truth), counts), strict=True):
        before = np.full((max_collaborators, 2), np.nan)
        after = np.full((max_collaborators, 2), np.nan)
        before[: errors_before.shape[0]] = errors_before
        after[: errors_after.shape[0]] = errors_after
        out.append((before, after))
    return out


def evaluate_egos(views: Sequence[EgoView], fused: Sequence[FusedDetections],
                  corrected: Sequence[np.ndarray], state: WorldState, visible: np.ndarray,
                  x_range: Sequence[float], y_range: Sequence[float],
                  max_collaborators: int, convention: str = "visible",
                  z_range: Sequence[float] = (-3.0, 1.0)) -> list[EgoEvaluation]:
    """Score each ego's fused detections against its ground truth (one frame, several egos).

    fused[k] and corrected[k] ((n_k, 3) corrected T_{j->i} of the filled slots, the
    poses the fusion used) belong to views[k]. convention / z_range: the ground truth's
    (:func:`ground_truths`). Transforms, range tests and the matching
    (:func:`~roco_env.metrics.match_frames`) are batched over the egos.
    """
    gts = ground_truths(state, visible, [(v.agent, truth_collaborators(v)) for v in views],
                        x_range, y_range, convention, z_range)
    counts = [len(f) for f in fused]
    all_fused = np.concatenate([np.zeros((0, 7)), *(f.boxes for f in fused)])
    in_range = _split(in_range_mask(all_fused, x_range, y_range), counts)
    errors = slot_errors(views, corrected, max_collaborators)
    preds = [(ego_fused.boxes[keep], ego_fused.scores[keep])
             for ego_fused, keep in zip(fused, in_range, strict=True)]
    all_stats = match_frames([(boxes, scores, gt_boxes) for (boxes, scores), (gt_boxes, _)
                              in zip(preds, gts, strict=True)], DEFAULT_IOU_THRESHOLDS)
    evaluations = []
    for (gt_boxes, _), (pred_boxes, pred_scores), stats, (before, after) in zip(
            gts, preds, all_stats, errors, strict=True):
        ap = dict(zip(stats.thresholds,
                      average_precisions(stats.scores, stats.tp, stats.n_gt).tolist(),
                      strict=True))
        evaluations.append(
            EgoEvaluation(gt_boxes, pred_boxes, pred_scores, stats, ap, before, after))
    return evaluations


def _split(values: np.ndarray, counts: Sequence[int]) -> list[np.ndarray]:
    """Consecutive chunks of ``values`` (along axis 0) of the given sizes."""
    return np.split(values, np.cumsum(counts)[:-1]) if len(counts) else []


class Reward(Protocol):
    """The reward stage (roco_env.stages, kind ``reward``): a scalar per evaluated agent
    and step. Its factory is called with the scenario's
    :class:`~roco_env.scenario.EvaluationConfig` (``reward`` names it; a registered
    reward reads its ``reward_params`` there)."""

    #: Whether it needs the evaluation of the ego's own boxes alone (the env then fuses
    #: and scores them too).
    needs_alone: bool

    def __call__(self, evaluation: EgoEvaluation, alone: EgoEvaluation | None) -> float:
        """The reward of ``evaluation``; ``alone`` is given when :attr:`needs_alone`."""


@dataclass(frozen=True)
class APReward:
    """``ap30`` / ``ap50`` / ``ap70``: the per-step AP at the IoU ``threshold``, with a
    NaN AP (no GT and no predictions: nothing to get right) counted as 0."""

    threshold: float
    needs_alone: ClassVar[bool] = False

    @classmethod
    def from_config(cls, config: EvaluationConfig) -> APReward:
        return cls(_reward_threshold(config.reward))

    def __call__(self, evaluation: EgoEvaluation, alone: EgoEvaluation | None = None) -> float:
        return _ap_or_zero(evaluation, self.threshold)


@dataclass(frozen=True)
class APGainReward(APReward):
    """``ap30_gain`` / ``ap50_gain`` / ``ap70_gain``: that AP minus the AP of the ego's own
    boxes alone on the same frame and ground truth, so a collaboration that adds nothing
    scores 0 and one that harms scores below 0."""

    needs_alone: ClassVar[bool] = True

    def __call__(self, evaluation: EgoEvaluation, alone: EgoEvaluation | None = None) -> float:
        if alone is None:
            raise ValueError(f"reward ap{round(self.threshold * 100)}_gain needs the "
                             "evaluation of the ego's own boxes alone")
        return _ap_or_zero(evaluation, self.threshold) - _ap_or_zero(alone, self.threshold)


class NegativeRPEReward:
    """``neg_rpe``: minus the mean over filled slots of (translation error m + rotation
    error deg) after correction; 0 without collaborators."""

    needs_alone = False

    @classmethod
    def from_config(cls, config: EvaluationConfig) -> NegativeRPEReward:
        return cls()

    def __call__(self, evaluation: EgoEvaluation, alone: EgoEvaluation | None = None) -> float:
        rows = evaluation.rpe_after[~np.isnan(evaluation.rpe_after).any(axis=1)]
        return -float(rows.sum(axis=1).mean()) if rows.shape[0] else 0.0


def _reward_threshold(name: str) -> float:
    """The IoU threshold of AP reward ``name`` (``ap70`` or ``ap70_gain``: 0.7)."""
    thresholds = {key: thr for thr, key in AP_KEYS.items()}
    return thresholds[name.removesuffix("_gain")]


def make_reward(config: EvaluationConfig) -> Reward:
    """The reward stage ``config.reward`` names (roco_env.stages)."""
    return stage("reward", config.reward).load_factory()(config)


def _ap_or_zero(evaluation: EgoEvaluation, threshold: float) -> float:
    """The frame's AP at ``threshold``; 0 where it is undefined (no GT, no predictions)."""
    value = evaluation.ap[threshold]
    return 0.0 if np.isnan(value) else float(value)


UNDEFINED = -1.0
"""Info sentinel: an AP with nothing to score (no GT, no predictions) and the RPE row of
an empty collaborator slot. Both quantities are >= 0 when defined, and infos hold no
NaN, so two runs' infos compare equal with ``==`` (PettingZoo's and Gymnasium's
determinism checks do so)."""


def info_capacity(max_boxes: int, max_collaborators: int) -> int:
    """Rows of the padded per-frame info arrays: (N + 1) x K.

    An ego fuses at most its own K boxes and K boxes of each of its N collaborator
    slots, so the fused predictions never exceed this; ground truth beyond it is cut
    (nearest first, ``n_gt`` keeps the full count).
    """
    return int(max_boxes) * (int(max_collaborators) + 1)


def rpe_info(errors: np.ndarray) -> np.ndarray:
    """An (N, 2) RPE array for an info: NaN rows of empty slots become :data:`UNDEFINED`."""
    return np.where(np.isnan(errors), UNDEFINED, errors)


def filled_rpe_rows(errors: np.ndarray) -> np.ndarray:
    """The rows of an info's (N, 2) ``rpe_before``/``rpe_after`` that belong to filled slots."""
    errors = np.asarray(errors, dtype=float).reshape(-1, 2)
    return errors[(errors >= 0).all(axis=1)]


def info_frame_stats(info: Mapping) -> FrameStats:
    """The frame's matching (:meth:`APAccumulator.add_stats` input) from a step info."""
    keep = np.asarray(info["fused_mask"], dtype=bool)
    return FrameStats(np.asarray(info["frame_scores"])[keep], np.asarray(info["frame_tp"])[:, keep],
                      np.asarray(info["frame_fp"])[:, keep], int(info["frame_n_gt"]),
                      DEFAULT_IOU_THRESHOLDS)


def _padded(rows: np.ndarray, capacity: int, axis: int = 0) -> np.ndarray:
    """``rows`` zero-padded along ``axis`` to ``capacity`` entries (same dtype).

    A zero array filled in place, many times faster than ``np.pad`` (some 30 calls a
    step; docs/performance.md)."""
    shape = list(rows.shape)
    shape[axis] = capacity
    out = np.zeros(shape, dtype=rows.dtype)
    out[(slice(None),) * axis + (slice(0, rows.shape[axis]),)] = rows
    return out


def metric_info(evaluation: EgoEvaluation, capacity: int) -> dict:
    """The metric entries of a step's info (keys of the env contract plus the boxes).

    Fixed shapes, no NaN: the per-prediction arrays are padded to ``capacity`` rows
    (:func:`info_capacity`; ``fused_mask`` marks the real ones, which come first,
    in descending score), ``gt_boxes`` likewise (``gt_mask``), undefined APs and
    empty RPE slots hold :data:`UNDEFINED`.
    """
    stats = evaluation.stats
    n_pred = int(evaluation.pred_scores.shape[0])
    if n_pred > capacity:
        raise ValueError(f"{n_pred} fused predictions exceed the info capacity {capacity}")
    gt = evaluation.gt_boxes
    nearest = np.argsort(np.hypot(gt[:, 0], gt[:, 1]), kind="stable")[:capacity]
    info = {key: UNDEFINED if np.isnan(evaluation.ap[thr]) else float(evaluation.ap[thr])
            for thr, key in AP_KEYS.items()}
    info.update(
        rpe_before=rpe_info(evaluation.rpe_before),
        rpe_after=rpe_info(evaluation.rpe_after),
        n_gt=int(gt.shape[0]),
        n_pred=n_pred,
        fused_mask=np.arange(capacity) < n_pred,
        frame_scores=_padded(stats.scores, capacity),
        frame_tp=_padded(stats.tp, capacity, axis=1),
        frame_fp=_padded(stats.fp, capacity, axis=1),
        frame_n_gt=stats.n_gt,
        fused_boxes=_padded(evaluation.pred_boxes, capacity),
        fused_scores=_padded(evaluation.pred_scores, capacity),
        gt_boxes=_padded(gt[nearest], capacity),
        gt_mask=np.arange(capacity) < nearest.shape[0],
    )
    return info
