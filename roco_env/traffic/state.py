"""The per-step world snapshot every later stage reads.

All boxes and poses are in the world frame of docs/conventions.md (right-handed,
x forward, y left, yaw in radians CCW from +x). Sizes are full lengths in metres.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

OBJECT_CLASSES = ("car", "van", "truck", "bus")
AGENT_KINDS = ("cav", "rsu")


@dataclass(frozen=True)
class WorldState:
    """Immutable snapshot of one time step.

    Objects (M of them): every vehicle in the scene, CAVs included.
      object_ids (M,) int64, stable across the episode.
      object_classes (M,) int64 index into OBJECT_CLASSES.
      object_boxes (M, 7) float64 world boxes (x, y, z, l, w, h, yaw).
      object_velocities (M, 2) float64 world velocity (m/s).
    Agents (A of them): CAVs first (cav_0, cav_1, ...), then RSUs (rsu_0, ...).
      agent_ids tuple of str; agent_kinds tuple of "cav" | "rsu".
      agent_poses (A, 3) true world poses (x, y, yaw) of the sensor origin.
      agent_object_ids (A,) int64: the object id of the agent's own vehicle,
        -1 for an RSU (an RSU is not an object others can see).
      sensor_heights (A,) metres above the ground under the agent;
      sensor_ranges (A,) metres; comm_ranges (A,) metres.
      ground_heights (A,) world z (m) of the ground under each agent (default 0):
        sensing measures heights (box tops and bottoms, the sensor) from it, so
        a recording whose world z is far from 0 (a DAIR-V2X scene at ~20 m, a
        V2XSet town on a hill) is seen as on flat ground at z = 0.
    """

    time: float
    object_ids: np.ndarray
    object_classes: np.ndarray
    object_boxes: np.ndarray
    object_velocities: np.ndarray
    agent_ids: tuple[str, ...]
    agent_kinds: tuple[str, ...]
    agent_poses: np.ndarray
    agent_object_ids: np.ndarray
    sensor_heights: np.ndarray
    sensor_ranges: np.ndarray
    comm_ranges: np.ndarray
    ground_heights: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.ground_heights is None:
            object.__setattr__(self, "ground_heights", np.zeros(len(self.agent_ids)))
        for name in (
            "object_ids", "object_classes", "object_boxes", "object_velocities",
            "agent_poses", "agent_object_ids", "sensor_heights", "sensor_ranges", "comm_ranges",
            "ground_heights",
        ):
            arr = np.array(getattr(self, name))  # private copy, then frozen
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    @property
    def num_objects(self) -> int:
        return int(self.object_ids.shape[0])

    @property
    def num_agents(self) -> int:
        return len(self.agent_ids)


class TrafficSource(Protocol):
    """Where objects and agents are, step by step. Deterministic given the rng.

    Sources with a fixed number of frames (replays, user frames) also have a
    ``finished`` property, True once the current frame is the last one.
    """

    def reset(self, rng: np.random.Generator) -> WorldState: ...

    def step(self, dt: float) -> WorldState: ...
