"""What collaborators send to an ego: reported pose, boxes, uncertainties, scores, features.

Collaborators of ego i are the other agents within i's communication range
(``state.comm_ranges[i]`` unless given), by TRUE BEV distance between sensor
origins, nearest first (ties by agent index), at most ``max_collaborators``.
A message carries only what the sender knows: its REPORTED (noisy) world pose
and its detections in its own sensor frame. Truth (object ids, true poses)
never enters a message.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from roco_env.sensing.detector import AgentDetections
from roco_env.traffic.state import WorldState

if TYPE_CHECKING:  # features are torch tensors; torch loads only when features are on
    import torch

__all__ = ["Message", "select_collaborators", "build_messages"]


@dataclass(frozen=True)
class Message:
    """One collaborator's transmission to an ego.

    sender: agent id; reported_pose (3,) the sender's noisy world pose (x m, y m,
    yaw rad); boxes (K, 7), uncertainty (K, 3) (sigma_x m, sigma_y m, sigma_yaw
    rad) and scores (K,) in the sender's own frame; features (C, H, W) float32
    in the sender's frame, or None.
    """

    sender: str
    reported_pose: np.ndarray
    boxes: np.ndarray
    uncertainty: np.ndarray
    scores: np.ndarray
    features: torch.Tensor | None = None


def select_collaborators(state: WorldState, ego_index: int, max_collaborators: int,
                         comm_range: float | None = None) -> list[int]:
    """Agent indices of ego's collaborators, nearest first (see module docstring).

    Raises ValueError for an ego index out of range, a negative
    ``max_collaborators`` or a non-positive ``comm_range``.
    """
    n_agents = state.num_agents
    if not 0 <= ego_index < n_agents:
        raise ValueError(f"ego_index must be in [0, {n_agents}); got {ego_index}")
    if max_collaborators < 0:
        raise ValueError(f"max_collaborators must be >= 0; got {max_collaborators}")
    limit = float(state.comm_ranges[ego_index]) if comm_range is None else float(comm_range)
    if not limit > 0.0:
        raise ValueError(f"comm_range must be > 0 m; got {limit}")
    poses = np.asarray(state.agent_poses, dtype=float)
    dist = np.hypot(*(poses[:, :2] - poses[ego_index, :2]).T)
    dist[ego_index] = np.inf
    order = np.argsort(dist, kind="stable")
    return [int(j) for j in order[dist[order] <= limit][:max_collaborators]]


def build_messages(state: WorldState, ego_index: int, reported_poses: np.ndarray,
                   detections: Sequence[AgentDetections], max_collaborators: int,
                   features: Sequence[torch.Tensor | None] | None = None,
                   comm_range: float | None = None) -> list[Message]:
    """Messages from ego's collaborators, in :func:`select_collaborators` order.

    reported_poses (A, 3) noisy world poses; detections one per agent (agent
    frames); features optional, one per agent (or None).
    """
    reported_poses = np.asarray(reported_poses, dtype=float)
    if reported_poses.shape != (state.num_agents, 3):
        raise ValueError(
            f"reported_poses must have shape ({state.num_agents}, 3); got {reported_poses.shape}"
        )
    if len(detections) != state.num_agents:
        raise ValueError(
            f"detections must hold one entry per agent ({state.num_agents}); got {len(detections)}"
        )
    if features is not None and len(features) != state.num_agents:
        raise ValueError(
            f"features must hold one entry per agent ({state.num_agents}); got {len(features)}"
        )
    return [
        Message(
            sender=state.agent_ids[j],
            reported_pose=reported_poses[j].copy(),
            boxes=detections[j].boxes.copy(),
            uncertainty=detections[j].uncertainty.copy(),
            scores=detections[j].scores.copy(),
            features=None if features is None else features[j],
        )
        for j in select_collaborators(state, ego_index, max_collaborators, comm_range)
    ]
