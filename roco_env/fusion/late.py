"""Late fusion of boxes (DESIGN.md section 7).

Each collaborator's boxes, given in that collaborator's own (true sensor)
frame, are moved into the ego frame with the *corrected* relative pose
``T_{j->i}``, merged with the ego's own boxes and reduced by rotated NMS in BEV
(OpenCOOD's default IoU threshold 0.15). The result is sorted by score,
highest first. Units: metres and radians; every box is (x, y, z, l, w, h, yaw).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from roco_env.fusion.nms import batched_nms_bev
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
    ego_boxes = validate_boxes(ego_boxes, "ego_boxes")
    ego_scores = _scores(ego_scores, ego_boxes, "ego_scores")
    relative_poses = np.asarray(relative_poses, dtype=float).reshape(-1, 3)
    if not (len(collab_boxes) == len(collab_scores) == relative_poses.shape[0]):
        raise ValueError(
            "collab_boxes, collab_scores and relative_poses must have one entry per collaborator; "
            f"got {len(collab_boxes)}, {len(collab_scores)} and {relative_poses.shape[0]}"
        )
    slot_boxes = [validate_boxes(b, f"collab_boxes[{slot}]") for slot, b in enumerate(collab_boxes)]
    slot_scores = [_scores(sc, b, f"collab_scores[{slot}]")
                   for slot, (sc, b) in enumerate(zip(collab_scores, slot_boxes, strict=True))]
    counts = np.array([b.shape[0] for b in slot_boxes], dtype=np.int64)
    slots = np.repeat(np.arange(counts.shape[0]), counts)
    # One transform for all collaborators: each box with its slot's pose.
    moved = transform_boxes(np.concatenate([np.zeros((0, 7)), *slot_boxes]),
                            relative_poses[slots])
    return FusedDetections(
        np.concatenate([ego_boxes, moved]),
        np.concatenate([ego_scores, *slot_scores]),
        np.concatenate([np.full(ego_boxes.shape[0], EGO_SOURCE), slots]).astype(np.int64),
        np.concatenate([np.arange(ego_boxes.shape[0]), np.arange(slots.shape[0])
                        - np.repeat(np.cumsum(counts) - counts, counts)]).astype(np.int64),
    )


def late_fusion(
    ego_boxes: np.ndarray,
    ego_scores: np.ndarray,
    collab_boxes: Sequence[np.ndarray],
    collab_scores: Sequence[np.ndarray],
    relative_poses: np.ndarray,
    nms_iou: float = 0.15,
) -> FusedDetections:
    """Late fusion of one ego: merge into the ego frame, then rotated BEV NMS at ``nms_iou``.

    Ties in score keep the ego's boxes first, then slot order.
    """
    merged = merge_into_ego_frame(ego_boxes, ego_scores, collab_boxes, collab_scores,
                                  relative_poses)
    return suppress([merged], nms_iou)[0]


def suppress(merged: Sequence[FusedDetections], nms_iou: float = 0.15) -> list[FusedDetections]:
    """NMS of several egos' merged boxes at once (one batched IoU computation).

    Each result equals ``geometry.nms_bev`` on that ego's boxes; see
    :mod:`roco_env.fusion.nms`.
    """
    kept = batched_nms_bev([m.boxes for m in merged], [m.scores for m in merged], nms_iou)
    return [
        FusedDetections(m.boxes[k], m.scores[k], m.source[k], m.source_index[k])
        for m, k in zip(merged, kept, strict=True)
    ]


def _scores(scores: np.ndarray, boxes: np.ndarray, name: str) -> np.ndarray:
    scores = np.asarray(scores, dtype=float).reshape(-1)
    if scores.shape[0] != boxes.shape[0]:
        raise ValueError(f"{name} must have one score per box ({boxes.shape[0]}); "
                         f"got {scores.shape[0]}")
    return scores
