"""Matching precision/recall of an alignment result against true object identities.

Definitions (box pairs are unordered; a "box" is (slot, box index), slot -1 = ego):

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

import numpy as np

from roco_env.policies.base import AlignmentResult

__all__ = ["matching_precision_recall"]


def _box_table(ego_ids: np.ndarray, collab_ids: np.ndarray) -> np.ndarray:
    """ids (N + 1, K): row 0 the ego, row j + 1 collaborator slot j."""
    k = max(ego_ids.size, collab_ids.shape[1] if collab_ids.ndim == 2 else 0)
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
    table = _box_table(ego_ids, collab_ids)
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
