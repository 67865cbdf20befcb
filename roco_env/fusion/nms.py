"""Rotated BEV NMS for many independent box sets at once (one per ego).

Same rule and result as :func:`roco_env.geometry.nms_bev` (visit boxes by
descending score, ties in input order; drop a box whose BEV IoU with an
already kept box exceeds the threshold), computed differently because the env
runs one NMS per ego per step and the exact IoU has a fixed cost per call:

* only pairs (earlier, later) in visiting order are evaluated (nms_bev builds
  the full symmetric matrix, diagonal included);
* pairs whose circumscribed circles do not overlap (nms_bev's own test, the
  candidates found with scipy's KD-tree instead of a dense distance matrix)
  have IoU 0 and are skipped;
* the remaining pairs of all sets go through ONE call of
  :func:`roco_env.geometry.bev_iou_pairs` (same argument order as nms_bev, so
  the IoU values are bit-identical).

Written here because no library offers batched rotated NMS on CPU/numpy
(torchvision's NMS is axis-aligned).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree

from roco_env.geometry import bev_iou_pairs, validate_boxes


def batched_nms_bev(boxes: Sequence[np.ndarray], scores: Sequence[np.ndarray],
                    iou_threshold: float) -> list[np.ndarray]:
    """Kept indices per set (highest score first), as ``nms_bev`` would return for each.

    boxes[g] (N_g, 7), scores[g] (N_g,); iou_threshold in [0, 1].
    """
    if len(boxes) != len(scores):
        raise ValueError(f"boxes and scores must hold the same number of sets; "
                         f"got {len(boxes)} and {len(scores)}")
    if not 0.0 <= iou_threshold <= 1.0:
        raise ValueError(f"iou_threshold must be in [0, 1]; got {iou_threshold}")
    orders, ranked = [], []
    for g, (set_boxes, set_scores) in enumerate(zip(boxes, scores, strict=True)):
        set_boxes = validate_boxes(set_boxes, f"boxes[{g}]")
        set_scores = np.asarray(set_scores, dtype=float).reshape(-1)
        if set_scores.shape[0] != set_boxes.shape[0] or not np.all(np.isfinite(set_scores)):
            raise ValueError(f"scores[{g}] must hold one finite score per box "
                             f"({set_boxes.shape[0]}); got shape {set_scores.shape}")
        orders.append(np.argsort(-set_scores, kind="stable"))
        ranked.append(set_boxes[orders[-1]])
    sizes = np.array([order.shape[0] for order in orders], dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(sizes)])
    stacked = np.concatenate(ranked).reshape(-1, 7) if ranked else np.zeros((0, 7))
    set_of = np.repeat(np.arange(len(orders)), sizes)
    first, second = _overlap_candidates(stacked, set_of)
    suppressing = bev_iou_pairs(stacked[first], stacked[second]) > iou_threshold
    first, second = first[suppressing], second[suppressing]
    kept = []
    for g, order in enumerate(orders):
        mine = set_of[first] == g
        local = _greedy(order.shape[0], first[mine] - starts[g], second[mine] - starts[g])
        kept.append(order[local])
    return kept


def _overlap_candidates(boxes: np.ndarray, set_of: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (i < j) of the same set whose circumscribed circles overlap.

    Neighbour search with one scipy KD-tree over all sets (sets kept apart on a
    third axis; O(n log n), no dense n x n matrix), then the same circle test as
    ``geometry.bev_iou`` on the exact coordinates.
    """
    empty = np.zeros(0, dtype=np.int64)
    if boxes.shape[0] < 2:
        return empty, empty
    radius = 0.5 * np.hypot(boxes[:, 3], boxes[:, 4])
    reach = 2.0 * radius.max()
    points = np.column_stack([boxes[:, :2], set_of * (4.0 * reach + 1.0)])
    pairs = cKDTree(points).query_pairs(reach, output_type="ndarray")
    if pairs.shape[0] == 0:
        return empty, empty
    first, second = pairs[:, 0], pairs[:, 1]  # i < j; their order does not matter
    gap = np.hypot(boxes[first, 0] - boxes[second, 0], boxes[first, 1] - boxes[second, 1])
    near = (gap < radius[first] + radius[second]) & (set_of[first] == set_of[second])
    return first[near], second[near]


def _greedy(n: int, first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """Greedy suppression over ranks 0..n-1 given suppressing pairs (earlier, later)."""
    neighbours: list[list[int]] = [[] for _ in range(n)]
    for i, j in zip(first.tolist(), second.tolist(), strict=True):
        neighbours[i].append(j)
    suppressed = [False] * n
    kept = []
    for rank in range(n):
        if suppressed[rank]:
            continue
        kept.append(rank)
        for j in neighbours[rank]:
            suppressed[j] = True
    return np.asarray(kept, dtype=np.int64)
