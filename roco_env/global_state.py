"""The global state for centralised critics: one fixed-size vector of the whole scene.

``env.state()`` returns it for the frame the agents observe now, ``env.state_space``
is its Box. Layout (float32; world frame; metres and radians; A agents in
``possible_agents`` order, M = ``max_objects`` box slots):

==========================  ==================================================
slice                       content
==========================  ==================================================
``[0, 3A)``                 true poses (x, y, yaw) of the agents' sensors
``[3A, 6A)``                reported (noisy) poses, what the agents broadcast
``[6A, 6A + 7M)``           ground-truth boxes (x, y, z, l, w, h, yaw), one per slot
``[6A + 7M, 6A + 8M)``      box mask: 1 = filled slot, 0 = padding (all-zero box)
==========================  ==================================================

Every vehicle in the scene is a ground-truth box (the CAVs' own cars included).
Boxes fill the slots nearest first, by BEV distance to the nearest agent; a scene
with more than M vehicles leaves the farthest out. :func:`unpack_state` splits a
vector back into named arrays.
"""

from __future__ import annotations

import numpy as np
from gymnasium import spaces

from roco_env.traffic.state import WorldState

__all__ = ["pack_state", "state_space", "unpack_state"]


def state_space(num_agents: int, max_objects: int) -> spaces.Box:
    """The Box of :func:`pack_state` vectors: 6 A + 8 M float32 values."""
    size = 6 * num_agents + 8 * max_objects
    low = np.full(size, -np.inf, dtype=np.float32)
    high = np.full(size, np.inf, dtype=np.float32)
    low[-max_objects:], high[-max_objects:] = 0.0, 1.0
    return spaces.Box(low=low, high=high, dtype=np.float32)


def pack_state(world: WorldState, reported_poses: np.ndarray, max_objects: int) -> np.ndarray:
    """The global state vector of ``world`` (layout in the module docstring)."""
    boxes = np.asarray(world.object_boxes, dtype=float).reshape(-1, 7)
    agents = np.asarray(world.agent_poses, dtype=float).reshape(-1, 3)
    if boxes.shape[0] > max_objects:
        gaps = np.hypot(*(boxes[:, None, :2] - agents[None, :, :2]).transpose(2, 0, 1))
        boxes = boxes[np.argsort(gaps.min(axis=1), kind="stable")[:max_objects]]
    slots = np.zeros((max_objects, 7))
    slots[: boxes.shape[0]] = boxes
    mask = np.zeros(max_objects)
    mask[: boxes.shape[0]] = 1.0
    parts = [agents.ravel(), np.asarray(reported_poses, dtype=float).ravel(), slots.ravel(), mask]
    return np.concatenate(parts).astype(np.float32)


def unpack_state(state: np.ndarray, num_agents: int, max_objects: int) -> dict[str, np.ndarray]:
    """Named views of a state vector: ``true_poses`` (A, 3), ``reported_poses`` (A, 3),
    ``boxes`` (M, 7) and ``box_mask`` (M,) bool."""
    state = np.asarray(state)
    a, m = num_agents, max_objects
    if state.shape != (6 * a + 8 * m,):
        raise ValueError(f"state must have shape ({6 * a + 8 * m},) for {a} agents and "
                         f"{m} box slots; got {state.shape}")
    return {
        "true_poses": state[: 3 * a].reshape(a, 3),
        "reported_poses": state[3 * a: 6 * a].reshape(a, 3),
        "boxes": state[6 * a: 6 * a + 7 * m].reshape(m, 7),
        "box_mask": state[6 * a + 7 * m:] > 0.5,
    }
