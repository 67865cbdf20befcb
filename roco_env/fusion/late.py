"""Late fusion of boxes (docs/architecture.md, step 3).

Each collaborator's boxes, given in that collaborator's own (true sensor)
frame, are moved into the ego frame with the *corrected* relative pose
``T_{j->i}``, merged with the ego's own boxes and reduced by rotated NMS in BEV
(OpenCOOD's default IoU threshold 0.15). The result is sorted by score,
highest first. Units: metres and radians; every box is (x, y, z, l, w, h, yaw).

Ego footprint: collaborators see the ego's own vehicle, but nothing the ego
detects can stand where the ego stands, and the ground truth leaves the ego
out (docs/metrics.md), so such boxes can only be false positives. A CAV
ego passes its own footprint (its object box in its own true frame; RSUs have
none) and every merged box whose BEV IoU with it exceeds the NMS threshold is
dropped before the NMS. This is exactly NMS with the footprint as an extra box
visited first, and it is the ego's most certain "detection": it suppresses what
any kept box would suppress. IoU rather than "centre inside the footprint"
because a collaborator's view of the ego arrives shifted by the pose error: a
car (4.5 m x 1.9 m) moved 1 m sideways has its centre outside the footprint but
IoU 0.31, and it stays above 0.15 up to a sideways shift of about 1.3 m or a
lengthwise shift of about 3 m; a neighbour's box, physically disjoint from the
ego and off by a few decimetres of detection noise, stays far below 0.15.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from roco_env.batched_nms import batched_nms_unchecked
from roco_env.geometry import transform_boxes, validate_boxes

EGO_SOURCE = -1


@dataclass(frozen=True)
class FusedDetections:
    """The ego's fused detections, in the ego frame.

    boxes (P, 7) float64, scores (P,) float64 sorted descending;
    source (P,) int64: -1 for the ego's own box, else the collaborator slot;
    source_index (P,) int64: the box's row in its source's box array.
    """

    boxes: np.ndarray
    scores: np.ndarray
    source: np.ndarray
    source_index: np.ndarray

    def __len__(self) -> int:
        return int(self.scores.shape[0])


def merge_into_ego_frame(
    ego_boxes: np.ndarray,
    ego_scores: np.ndarray,
    collab_boxes: Sequence[np.ndarray],
    collab_scores: Sequence[np.ndarray],
    relative_poses: np.ndarray,
) -> FusedDetections:
    """Concatenate the ego's boxes with every collaborator's boxes moved into the ego frame.

    relative_poses (N, 3): T_{j->i} per collaborator slot (x m, y m, yaw rad),
    the poses the boxes are moved with (corrected ones for fusion). No NMS.
    """
    return _merge([_checked_ego(ego_boxes, ego_scores, collab_boxes, collab_scores,
                                relative_poses, "")])[0]


def merge_many(egos: Sequence[tuple]) -> list[FusedDetections]:
    """:func:`merge_into_ego_frame` of several egos, one box transform for all of them.

    egos[k] = (ego_boxes, ego_scores, collab_boxes, collab_scores, relative_poses),
    the arguments of :func:`merge_into_ego_frame`; errors name ``egos[k]``.
    """
    checked = []
    for k, ego in enumerate(egos):
        if len(ego) != 5:
            raise ValueError(f"egos[{k}] must be (ego_boxes, ego_scores, collab_boxes, "
                             f"collab_scores, relative_poses); got {len(ego)} items")
        checked.append(_checked_ego(*ego, f"egos[{k}]."))
    return _merge(checked)


@dataclass(frozen=True)
class _EgoInputs:
    """One ego's validated merge inputs; collab (sum K_j, 7) stacked by slot, counts (N,)."""

    boxes: np.ndarray
    scores: np.ndarray
    collab: np.ndarray
    collab_scores: np.ndarray
    counts: np.ndarray
    poses: np.ndarray


def _checked_ego(ego_boxes: np.ndarray, ego_scores: np.ndarray,
                 collab_boxes: Sequence[np.ndarray], collab_scores: Sequence[np.ndarray],
                 relative_poses: np.ndarray, prefix: str) -> _EgoInputs:
    ego_boxes = validate_boxes(ego_boxes, f"{prefix}ego_boxes")
    ego_scores = _scores(ego_scores, ego_boxes.shape[0], f"{prefix}ego_scores")
    relative_poses = np.asarray(relative_poses, dtype=float).reshape(-1, 3)
    if not (len(collab_boxes) == len(collab_scores) == relative_poses.shape[0]):
        raise ValueError(
            f"{prefix}collab_boxes, collab_scores and relative_poses must have one entry per "
            f"collaborator; got {len(collab_boxes)}, {len(collab_scores)} and "
            f"{relative_poses.shape[0]}"
        )
    stacked = _stacked_boxes(collab_boxes, f"{prefix}collab_boxes")
    counts = np.array([len(b) for b in collab_boxes], dtype=np.int64)
    slot_scores = [_scores(sc, n, f"{prefix}collab_scores[{slot}]")
                   for slot, (sc, n) in enumerate(zip(collab_scores, counts.tolist(), strict=True))]
    return _EgoInputs(ego_boxes, ego_scores, stacked, np.concatenate([np.zeros(0), *slot_scores]),
                      counts, relative_poses)


def _merge(egos: Sequence[_EgoInputs]) -> list[FusedDetections]:
    """Merged detections per ego; every collaborator box is moved in ONE transform."""
    slots = [np.repeat(np.arange(ego.counts.shape[0]), ego.counts) for ego in egos]
    moved = transform_boxes(np.concatenate([np.zeros((0, 7)), *(ego.collab for ego in egos)]),
                            np.concatenate([np.zeros((0, 3)), *(ego.poses[slot] for ego, slot
                                                                in zip(egos, slots, strict=True))]))
    sizes = [ego.collab.shape[0] for ego in egos]
    out = []
    for ego, slot, ego_moved in zip(egos, slots, np.split(moved, np.cumsum(sizes)[:-1]),
                                    strict=True):
        n_own = ego.boxes.shape[0]
        out.append(FusedDetections(
            np.concatenate([ego.boxes, ego_moved]),
            np.concatenate([ego.scores, ego.collab_scores]),
            np.concatenate([np.full(n_own, EGO_SOURCE), slot]).astype(np.int64),
            np.concatenate([np.arange(n_own), np.arange(slot.shape[0])
                            - np.repeat(np.cumsum(ego.counts) - ego.counts, ego.counts)]
                           ).astype(np.int64),
        ))
    return out


def late_fusion(
    ego_boxes: np.ndarray,
    ego_scores: np.ndarray,
    collab_boxes: Sequence[np.ndarray],
    collab_scores: Sequence[np.ndarray],
    relative_poses: np.ndarray,
    nms_iou: float = 0.15,
    ego_footprint: np.ndarray | None = None,
) -> FusedDetections:
    """Late fusion of one ego: merge into the ego frame, then rotated BEV NMS at ``nms_iou``.

    Ties in score keep the ego's boxes first, then slot order. ego_footprint (7,):
    the ego's own vehicle box in its frame (None: no footprint, e.g. an RSU);
    boxes overlapping it are dropped (module docstring).
    """
    merged = merge_into_ego_frame(ego_boxes, ego_scores, collab_boxes, collab_scores,
                                  relative_poses)
    if ego_footprint is not None:
        ego_footprint = _footprint(ego_footprint, "ego_footprint")[0]
    return suppress([merged], nms_iou, [ego_footprint])[0]


def suppress(merged: Sequence[FusedDetections], nms_iou: float = 0.15,
             footprints: Sequence[np.ndarray | None] | None = None) -> list[FusedDetections]:
    """NMS of several egos' merged boxes at once (one batched IoU computation).

    footprints[k]: ego k's own vehicle box (7,) in its frame, or None (an RSU);
    boxes overlapping it with BEV IoU > ``nms_iou`` are dropped (module
    docstring). Without footprints each result equals ``geometry.nms_bev`` on
    that ego's boxes; see :mod:`roco_env.batched_nms`.
    """
    if footprints is None:
        footprints = [None] * len(merged)
    if len(footprints) != len(merged):
        raise ValueError(f"footprints must hold one entry (box or None) per ego; got "
                         f"{len(footprints)} for {len(merged)} egos")
    _stacked_boxes([m.boxes for m in merged], "merged boxes")
    for k, m in enumerate(merged):
        if np.shape(m.scores) != (len(m.boxes),) or not np.all(np.isfinite(m.scores)):
            raise ValueError(f"merged[{k}].scores must hold one finite score per box "
                             f"({len(m.boxes)}); got shape {np.shape(m.scores)}")
    boxes, scores, shift = [], [], []
    for k, (m, footprint) in enumerate(zip(merged, footprints, strict=True)):
        if footprint is None:
            boxes.append(m.boxes)
            scores.append(m.scores)
        else:
            # First in the input with the highest score: NMS visits it first (ties keep
            # input order), so it is kept and suppresses whatever overlaps the ego.
            boxes.append(np.concatenate([_footprint(footprint, f"footprints[{k}]"), m.boxes]))
            scores.append(np.concatenate([[m.scores.max(initial=0.0)], m.scores]))
        shift.append(int(footprint is not None))
    kept = batched_nms_unchecked(boxes, scores, nms_iou)
    out = []
    for m, k, first in zip(merged, kept, shift, strict=True):
        k = k[first:] - first  # drop the footprint (kept first whenever present)
        out.append(FusedDetections(m.boxes[k], m.scores[k], m.source[k], m.source_index[k]))
    return out


def _footprint(footprint: np.ndarray, name: str) -> np.ndarray:
    """The footprint as a validated (1, 7) box array."""
    arr = np.asarray(footprint, dtype=float)
    if arr.shape not in ((7,), (1, 7)):
        raise ValueError(f"{name} must be one box (7,) = (x, y, z, l, w, h, yaw) or None; "
                         f"got shape {arr.shape}")
    return validate_boxes(arr.reshape(1, 7), name)


def _stacked_boxes(arrays: Sequence[np.ndarray], name: str) -> np.ndarray:
    """Box arrays stacked (sum K_j, 7), validated in one pass.

    A bad array raises ``validate_boxes``'s error naming it (``name[k]``): the
    arrays are checked one by one only when the stacked check fails.
    """
    try:
        return validate_boxes(np.concatenate([np.zeros((0, 7)), *arrays]), name)
    except ValueError:  # wrong shape, NaN or negative size somewhere (or an empty 1-D array)
        checked = [validate_boxes(b, f"{name}[{k}]") for k, b in enumerate(arrays)]
        return np.concatenate([np.zeros((0, 7)), *checked])


def _scores(scores: np.ndarray, n_boxes: int, name: str) -> np.ndarray:
    scores = np.asarray(scores, dtype=float).reshape(-1)
    if scores.shape[0] != n_boxes:
        raise ValueError(f"{name} must have one score per box ({n_boxes}); got {scores.shape[0]}")
    return scores


class LateFusion:
    """``late`` (the default): the ego's boxes and its kept collaborators' boxes, moved
    into the ego frame with the corrected poses (:func:`merge_many`)."""

    def __init__(self, config: Any = None, detector: Any = None) -> None:
        """The stage factory's signature; late fusion needs neither argument."""

    def fuse(self, frame: Any, egos: Sequence[int], kept: Sequence[np.ndarray],
             poses: Sequence[np.ndarray]) -> list[FusedDetections]:
        return merge_many([
            (frame.views[k].boxes, frame.views[k].scores,
             kept_items(frame.views[k].collab_boxes, keep),
             kept_items(frame.views[k].collab_scores, keep), pose)
            for k, keep, pose in zip(egos, kept, poses, strict=True)])


class NoFusion(LateFusion):
    """``none``: the ego's own boxes alone (the no-fusion reference row)."""

    def fuse(self, frame: Any, egos: Sequence[int], kept: Sequence[np.ndarray],
             poses: Sequence[np.ndarray]) -> list[FusedDetections]:
        return own_detections(frame, egos)


def own_detections(frame: Any, egos: Sequence[int]) -> list[FusedDetections]:
    """Each ego's own boxes as merged detections (no collaborator), in its true frame."""
    return merge_many([(frame.views[k].boxes, frame.views[k].scores, (), (), np.zeros((0, 3)))
                       for k in egos])


def kept_items(items: Sequence, keep: np.ndarray) -> list:
    """The entries of ``items`` (one per collaborator slot) whose slot ``keep`` keeps."""
    return [item for item, k in zip(items, keep, strict=True) if k]
