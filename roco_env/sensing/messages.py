"""What a collaborator sends an ego, and who collaborates with it.

Collaborators of ego i are the other agents within i's communication range
(``state.comm_ranges[i]`` unless given), by TRUE BEV distance between sensor
origins, nearest first (ties by agent index), at most ``max_collaborators``
(:func:`select_collaborators`). A :class:`Message` carries only what the sender
knows: its REPORTED (noisy) world pose and its detections in its own sensor frame.
Truth (object ids, true poses) never enters a message. The network stage
(:mod:`roco_env.comm`) carries the scans; the attack stage rewrites messages.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from roco_env.traffic.state import WorldState

__all__ = ["Message", "select_collaborators"]


@dataclass(frozen=True)
class Message:
    """One collaborator's transmission to an ego.

    sender: agent id; reported_pose (3,) the sender's noisy world pose (x m, y m,
    yaw rad); boxes (K, 7), uncertainty (K, 3) (sigma_x m, sigma_y m, sigma_yaw
    rad) and scores (K,) in the sender's own frame.
    """

    sender: str
    reported_pose: np.ndarray
    boxes: np.ndarray
    uncertainty: np.ndarray
    scores: np.ndarray


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
