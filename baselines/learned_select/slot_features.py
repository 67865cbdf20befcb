"""Per-slot features of a collaborator's boxes against the ego's (no truth; a probe input).

What an ego could compute from its ``aligned`` observation: its own boxes, each
collaborator's boxes moved into the ego frame by the pose the ego keeps for that slot
(the observation holds them moved by ``collab_rel_poses``, the reported pose in select
mode: they are moved back and then by the kept pose), their scores, and what late fusion
would make of them (the aligned observation carries no uncertainties). ``choice_probe.py
--features obs+slot`` appends these columns to the observation row, to ask whether they
predict "rejecting this well-aligned collaborator raises the ego's AP@0.7". Frames: boxes
(x, y, z, l, w, h, yaw) in m / rad, moved into the ego frame with T_{j->i}; a collaborator
box "matches" an ego box whose centre lies within :data:`MATCH_M` of its centre.
"""

from __future__ import annotations

import numpy as np

from roco_env.fusion.late import late_fusion
from roco_env.geometry import (
    bev_iou,
    bev_iou_pairs,
    se2_compose,
    se2_inverse,
    transform_boxes,
    wrap_angle,
)

MATCH_M = 2.0  # m between centres: a collaborator box and an ego box show the same object
NMS_IOU = 0.15  # the env's default late-fusion NMS threshold (ScenarioConfig.fusion.nms_iou)
NAMES = (
    "boxes",                # the slot's box count
    "share_matched",        # share of its boxes with an ego box within MATCH_M
    "median_matched_m",     # median centre distance to the nearest ego box, matched ones (m)
    "max_matched_m",        # the largest of those (m)
    "median_matched_yaw",   # median |yaw difference| to that ego box, matched ones (rad)
    "mean_matched_iou",     # mean BEV IoU with that ego box, matched ones
    "overlap_unmatched",    # boxes overlapping an ego box (IoU > 0) without matching it
    "new",                  # boxes with no ego box within MATCH_M (objects it adds)
    "mean_score",           # mean detection score of its boxes
    "min_score",            # the lowest
    "mean_new_score",       # mean score of the new boxes (0 if none)
    "mean_range_m",         # mean distance of its boxes from the collaborator's origin (m)
    "collaborator_m",       # distance of the collaborator from the ego (m, by the kept pose)
    "mean_others",          # mean number of other kept slots with a box within MATCH_M
    "new_alone",            # new boxes no other kept slot has a box within MATCH_M of
    "score_minus_ego",      # mean (its score - the matched ego box's score), matched ones
    "fused_from_slot",      # late-fused boxes (C's kept slots) that come from this slot
    "fused_replacing_ego",  # of those, ones within MATCH_M of an ego box (they replace it)
    "fused_shift_m",        # mean centre distance of those to the ego box they replace (m)
    "fused_new",            # fused boxes from this slot with no ego box within MATCH_M
)


def nearest(points: np.ndarray, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """((P,) index of the nearest of ``targets`` (T, 2), (P,) its distance, m) of each of
    ``points`` (P, 2); distance inf where there are no targets."""
    if len(targets) == 0:
        return np.zeros(len(points), dtype=np.int64), np.full(len(points), np.inf)
    distance = np.hypot(*(points[:, None, :] - targets[None, :, :]).transpose(2, 0, 1))
    index = np.argmin(distance, axis=1)
    return index, distance[np.arange(len(points)), index]


def _mean(values: np.ndarray, empty: float = 0.0) -> float:
    return float(np.mean(values)) if len(values) else empty


def _median(values: np.ndarray, empty: float) -> float:
    return float(np.median(values)) if len(values) else empty


def slot_features(observation: dict, poses: np.ndarray, kept: np.ndarray,
                  slots: np.ndarray) -> np.ndarray:
    """(len(slots), len(NAMES)) features (:data:`NAMES`) of each of ``slots`` (indices
    among the filled ones) of the ``aligned`` ``observation``: ``poses`` (n, 3) the T_{j->i}
    (x m, y m, yaw rad) the ego keeps for its n filled slots, ``kept`` (n,) bool the slots
    its action fuses (each listed slot's features count it as fused)."""
    own_mask = observation["box_mask"] > 0
    own = np.asarray(observation["boxes"], dtype=float)[own_mask]
    own_scores = np.asarray(observation["scores"], dtype=float)[own_mask]
    moved, scores, local = [], [], []
    for j in range(len(poses)):
        mask = observation["collab_box_mask"][j] > 0
        shown = np.asarray(observation["collab_boxes"][j], dtype=float)[mask]
        shown_by = se2_inverse(np.asarray(observation["collab_rel_poses"][j], dtype=float))
        local.append(transform_boxes(shown, shown_by))  # in the collaborator's frame
        moved.append(transform_boxes(shown, se2_compose(poses[j], shown_by)))
        scores.append(np.asarray(observation["collab_scores"][j], dtype=float)[mask])
    rows = []
    for j in slots:
        fused = kept.copy()
        fused[j] = True
        others = [k for k in np.flatnonzero(fused) if k != j]
        rows.append(_features(j, own, own_scores, moved, scores, local, poses,
                              others, np.flatnonzero(fused)))
    return np.array(rows, dtype=float).reshape(len(slots), len(NAMES))


def _features(j, own, own_scores, moved, scores, local, poses, others,
              fused_slots) -> list[float]:
    """One row of :func:`slot_features` (slot ``j``; ``others``: the other fused slots)."""
    boxes = moved[j]
    index, distance = nearest(boxes[:, :2], own[:, :2])
    matched = distance <= MATCH_M
    pairs = (boxes[matched], own[index[matched]])
    iou = bev_iou(boxes, own).max(axis=1, initial=0.0) if len(own) else np.zeros(len(boxes))
    new = ~matched
    near_others = np.array([nearest(boxes[:, :2], moved[k][:, :2])[1] <= MATCH_M
                            for k in others]).reshape(len(others), len(boxes))
    counts = near_others.sum(axis=0)
    result = late_fusion(own, own_scores, [moved[k] for k in fused_slots],
                         [scores[k] for k in fused_slots], np.zeros((len(fused_slots), 3)),
                         NMS_IOU)
    from_slot = result.source == list(fused_slots).index(j)
    _, fused_distance = nearest(result.boxes[from_slot, :2], own[:, :2])
    replacing = fused_distance <= MATCH_M
    return [
        len(boxes), _mean(matched), _median(distance[matched], MATCH_M),
        float(distance[matched].max()) if matched.any() else MATCH_M,
        _median(np.abs(wrap_angle(pairs[0][:, 6] - pairs[1][:, 6])), np.pi),
        _mean(bev_iou_pairs(*pairs)) if matched.any() else 0.0,
        int(np.sum(new & (iou > 0))), int(new.sum()),
        _mean(scores[j]), float(scores[j].min(initial=1.0)), _mean(scores[j][new]),
        _mean(np.hypot(local[j][:, 0], local[j][:, 1])),
        float(np.hypot(poses[j][0], poses[j][1])), _mean(counts),
        int(np.sum(new & (counts == 0))),
        _mean(scores[j][matched] - own_scores[index[matched]]),
        int(from_slot.sum()), int(replacing.sum()), _mean(fused_distance[replacing]),
        int(np.sum(~replacing)),
    ]

