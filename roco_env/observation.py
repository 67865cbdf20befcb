"""What one agent holds at one step, and its fixed-size observation.

:class:`EgoView` is the unpadded truth-annotated content of agent i's
observation (float64); :func:`observation_space` / :func:`pack_observation`
turn it into the padded gymnasium ``Dict`` of the contract (float32, masks int8)
with K = ``max_boxes`` box slots and N = ``max_collaborators`` collaborator slots,
nearest collaborator first, empty slots all zeros. Frames: the own boxes are
in the agent's (true sensor) frame, each collaborator's boxes in that
collaborator's own frame; poses are world poses (x m, y m, yaw rad) as reported
(noisy); ``collab_rel_poses`` holds the reported ``T_{j->i}``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from gymnasium import spaces

_F32 = np.float32


@dataclass(frozen=True)
class EgoView:
    """Agent i's view at one step (unpadded, float64) plus the truth about it.

    agent: index of the agent; pose (3,) its reported world pose (clean when the
    noise config has ``perturb_ego=False``); boxes (k, 7), uncertainty (k, 3),
    scores (k,), object_ids (k,) its own detections (ids: truth, -1 = false
    positive). collaborators: agent indices by slot (n <= N); collab_poses (n, 3)
    their reported world poses; reported_relative (n, 3) reported T_{j->i};
    true_relative (n, 3) true T_{j->i}; collab_boxes / collab_uncertainty /
    collab_scores / collab_object_ids: per slot, in the collaborator's frame.
    features: own BEV features, torch (C, H, W), or None; collab_features: per slot or None.
    With the network stage on (roco_env.comm): collab_age (n,) the age of each slot's
    scan, s; collab_new (n,) bool, whether it arrived this step; network: the agent's
    traffic info entries (time, bytes_sent, bytes_received, messages_lost);
    collab_map_rows: under intermediate fusion, each slot's row of the frame's encoder
    maps; in_range: the agents whose messages the ego would use now over an instant,
    lossless link (in communication range, nearest first, at most N: the collaboration
    its ground truth counts). All None with the network off (collab_map_rows: the slots'
    agent indices; in_range: the slots).
    """

    agent: int
    pose: np.ndarray
    boxes: np.ndarray
    uncertainty: np.ndarray
    scores: np.ndarray
    object_ids: np.ndarray
    collaborators: tuple[int, ...]
    collab_poses: np.ndarray
    reported_relative: np.ndarray
    true_relative: np.ndarray
    collab_boxes: tuple[np.ndarray, ...]
    collab_uncertainty: tuple[np.ndarray, ...]
    collab_scores: tuple[np.ndarray, ...]
    collab_object_ids: tuple[np.ndarray, ...]
    features: Any = None
    collab_features: tuple | None = None
    collab_age: np.ndarray | None = None
    collab_new: np.ndarray | None = None
    network: dict | None = None
    collab_map_rows: tuple[int, ...] | None = None
    in_range: tuple[int, ...] | None = None


def top_k(scores: np.ndarray, k: int) -> np.ndarray:
    """Indices of the ``k`` highest scores (ties: earlier first), in ascending index order."""
    scores = np.asarray(scores)
    if scores.shape[0] <= k:
        return np.arange(scores.shape[0])
    return np.sort(np.argsort(-scores, kind="stable")[:k])


def observation_space(max_boxes: int, max_collaborators: int,
                      feature_shape: tuple[int, int, int] | None = None,
                      timing: bool = False) -> spaces.Dict:
    """The Dict observation space of the contract (``features`` only when a shape is given;
    ``collab_age`` and ``collab_new`` only with ``timing``: the network stage on)."""
    k, n = max_boxes, max_collaborators

    def real(*shape: int, low: float = -np.inf, high: float = np.inf) -> spaces.Box:
        return spaces.Box(low=low, high=high, shape=shape, dtype=_F32)

    def mask(*shape: int) -> spaces.Box:
        return spaces.Box(low=0, high=1, shape=shape, dtype=np.int8)

    entries = {
        "pose": real(3),
        "boxes": real(k, 7),
        "uncertainty": real(k, 3, low=0.0),
        "scores": real(k, low=0.0, high=1.0),
        "box_mask": mask(k),
        "collab_mask": mask(n),
        "collab_poses": real(n, 3),
        "collab_rel_poses": real(n, 3),
        "collab_boxes": real(n, k, 7),
        "collab_uncertainty": real(n, k, 3, low=0.0),
        "collab_scores": real(n, k, low=0.0, high=1.0),
        "collab_box_mask": mask(n, k),
    }
    if timing:
        entries["collab_age"] = real(n, low=0.0)
        entries["collab_new"] = mask(n)
    if feature_shape is not None:
        entries["features"] = real(*feature_shape)
    return spaces.Dict(entries)


def action_space(max_collaborators: int, max_translation: float,
                 max_rotation: float = np.pi) -> spaces.Box:
    """Box (N, 3) float32 of corrections (dx, dy, dyaw).

    Bounds: |dx|, |dy| <= max_translation (m), |dyaw| <= max_rotation (rad).
    """
    bound = np.array([max_translation, max_translation, max_rotation], dtype=_F32)
    high = np.tile(bound, (max_collaborators, 1))
    return spaces.Box(low=-high, high=high, dtype=_F32)


def pack_observation(view: EgoView, max_boxes: int, max_collaborators: int,
                     with_features: bool) -> dict[str, np.ndarray]:
    """The padded observation dict of ``view`` (contract layout, see module docstring)."""
    k, n = max_boxes, max_collaborators
    obs = {
        "pose": view.pose.astype(_F32),
        "collab_mask": np.zeros(n, dtype=np.int8),
        "collab_poses": np.zeros((n, 3), dtype=_F32),
        "collab_rel_poses": np.zeros((n, 3), dtype=_F32),
        "collab_boxes": np.zeros((n, k, 7), dtype=_F32),
        "collab_uncertainty": np.zeros((n, k, 3), dtype=_F32),
        "collab_scores": np.zeros((n, k), dtype=_F32),
        "collab_box_mask": np.zeros((n, k), dtype=np.int8),
    }
    obs["boxes"], obs["uncertainty"], obs["scores"], obs["box_mask"] = _pad_boxes(
        view.boxes, view.uncertainty, view.scores, k)
    filled = len(view.collaborators)
    obs["collab_mask"][:filled] = 1
    obs["collab_poses"][:filled] = view.collab_poses
    obs["collab_rel_poses"][:filled] = view.reported_relative
    for slot in range(filled):
        count = view.collab_scores[slot].shape[0]
        obs["collab_boxes"][slot, :count] = view.collab_boxes[slot]
        obs["collab_uncertainty"][slot, :count] = view.collab_uncertainty[slot]
        obs["collab_scores"][slot, :count] = view.collab_scores[slot]
        obs["collab_box_mask"][slot, :count] = 1
    if view.collab_age is not None:
        obs["collab_age"] = np.zeros(n, dtype=_F32)
        obs["collab_new"] = np.zeros(n, dtype=np.int8)
        obs["collab_age"][:filled] = view.collab_age
        obs["collab_new"][:filled] = view.collab_new
    if with_features:
        obs["features"] = view.features.numpy().astype(_F32)  # a copy: never aliases state
    return obs


def privileged_truth(view: EgoView, max_boxes: int, max_collaborators: int) -> dict:
    """Truth about the observation of ``view``: relative poses (N, 3) float64, object ids.

    Empty slots hold zero poses and id -1 (the masks in the observation say which are real).
    """
    n = max_collaborators
    true_rel = np.zeros((n, 3))
    reported_rel = np.zeros((n, 3))
    filled = len(view.collaborators)
    true_rel[:filled] = view.true_relative
    reported_rel[:filled] = view.reported_relative
    box_ids = np.full(max_boxes, -1, dtype=np.int64)
    box_ids[: view.object_ids.shape[0]] = view.object_ids
    collab_ids = np.full((n, max_boxes), -1, dtype=np.int64)
    for slot in range(filled):
        collab_ids[slot, : view.collab_object_ids[slot].shape[0]] = view.collab_object_ids[slot]
    return {
        "true_relative_poses": true_rel,
        "reported_relative_poses": reported_rel,
        "box_object_ids": box_ids,
        "collab_box_object_ids": collab_ids,
    }


def _pad_boxes(boxes: np.ndarray, uncertainty: np.ndarray, scores: np.ndarray,
               k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    count = scores.shape[0]
    out_boxes = np.zeros((k, 7), dtype=_F32)
    out_unc = np.zeros((k, 3), dtype=_F32)
    out_scores = np.zeros(k, dtype=_F32)
    out_mask = np.zeros(k, dtype=np.int8)
    out_boxes[:count], out_unc[:count], out_scores[:count] = boxes, uncertainty, scores
    out_mask[:count] = 1
    return out_boxes, out_unc, out_scores, out_mask


def check_action(action: object, agent: str, max_collaborators: int) -> np.ndarray:
    """Validate one agent's action: an (N, 3) array of finite numbers; returns it as float64.

    Values outside the action space's bounds are accepted (not clipped): the
    bounds describe the useful range, the correction is applied as given.
    """
    try:
        raw = np.asarray(action)
        if raw.dtype.kind not in "iuf":  # bool and complex would convert silently
            raise TypeError(f"dtype {raw.dtype}")
        arr = raw.astype(float)
    except (TypeError, ValueError) as exc:
        raise ValueError(
            f"action for agent {agent!r} must be an array of real numbers (int or float) of "
            f"shape ({max_collaborators}, 3) = (dx m, dy m, dyaw rad) per collaborator slot; "
            f"got {exc}"
        ) from exc
    if arr.shape != (max_collaborators, 3):
        raise ValueError(
            f"action for agent {agent!r} must have shape ({max_collaborators}, 3) = "
            f"(dx m, dy m, dyaw rad) per collaborator slot; got {arr.shape}"
        )
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"action for agent {agent!r} contains NaN or inf; "
                         "all values must be finite")
    return arr
