"""Agents on top of vehicles: choosing CAVs, placing RSUs, assembling WorldState.

Shared by every traffic source so that agent naming (cav_0.., rsu_0..), sensor
settings (from ``config.agents``) and the CAV-is-an-object rule live in one place.
"""

from __future__ import annotations

import numpy as np

from roco_env.scenario import AgentsConfig
from roco_env.traffic.state import WorldState


def select_cavs(rng: np.random.Generator, centres: np.ndarray, scene_centre: np.ndarray,
                count: int, eligible: np.ndarray | None = None) -> np.ndarray:
    """Choose ``count`` vehicle indices near ``scene_centre`` (m), deterministically from rng.

    The pool is the ``max(2*count, 8)`` eligible vehicles nearest the centre, so that
    the chosen CAVs start within a few tens of metres of each other (well inside
    the default 70 m comm range). ``eligible`` (bool mask) restricts the choice,
    e.g. to vehicles approaching the centre. Raises ValueError when too few exist.
    """
    centres = np.asarray(centres, dtype=float).reshape(-1, 2)
    candidates = np.arange(centres.shape[0]) if eligible is None else np.flatnonzero(eligible)
    if candidates.size < count:
        raise ValueError(
            f"agents.cavs={count} but the scene has only {candidates.size} eligible vehicles; "
            "raise traffic.density or lower agents.cavs"
        )
    if count == 0:
        return np.zeros(0, dtype=np.int64)
    dist = np.hypot(*(centres[candidates] - np.asarray(scene_centre, dtype=float)).T)
    pool = candidates[np.argsort(dist, kind="stable")[: max(2 * count, 8)]]
    return np.sort(rng.choice(pool, size=count, replace=False)).astype(np.int64)


def rsu_poses(spots: np.ndarray, count: int, layout: str) -> np.ndarray:
    """The first ``count`` RSU poses (x, y, yaw) of a layout's ordered spot list."""
    spots = np.asarray(spots, dtype=float).reshape(-1, 3)
    if count > spots.shape[0]:
        raise ValueError(
            f"agents.rsus={count} but layout {layout!r} has {spots.shape[0]} RSU spots; "
            f"allowed: 0..{spots.shape[0]}"
        )
    return spots[:count]


def make_world(time: float, object_ids: np.ndarray, object_classes: np.ndarray,
               object_boxes: np.ndarray, object_velocities: np.ndarray,
               cav_objects: np.ndarray, rsu_pose_array: np.ndarray,
               agents: AgentsConfig) -> WorldState:
    """Assemble a WorldState: CAVs (rows ``cav_objects`` of the object arrays) then RSUs.

    CAV poses are their vehicles' (x, y, yaw); sensor heights, ranges and comm
    ranges come from ``agents``.
    """
    cav_objects = np.asarray(cav_objects, dtype=np.int64)
    rsu_pose_array = np.asarray(rsu_pose_array, dtype=float).reshape(-1, 3)
    n_cav, n_rsu = cav_objects.size, rsu_pose_array.shape[0]
    cav_poses = object_boxes[cav_objects][:, [0, 1, 6]]
    return WorldState(
        time=float(time),
        object_ids=object_ids,
        object_classes=object_classes,
        object_boxes=object_boxes,
        object_velocities=object_velocities,
        agent_ids=tuple(f"cav_{i}" for i in range(n_cav)) + tuple(f"rsu_{i}" for i in range(n_rsu)),
        agent_kinds=("cav",) * n_cav + ("rsu",) * n_rsu,
        agent_poses=np.concatenate([cav_poses, rsu_pose_array]).reshape(-1, 3),
        agent_object_ids=np.concatenate([object_ids[cav_objects], -np.ones(n_rsu, np.int64)]),
        sensor_heights=np.r_[np.full(n_cav, agents.cav_height), np.full(n_rsu, agents.rsu_height)],
        sensor_ranges=np.r_[np.full(n_cav, agents.cav_range), np.full(n_rsu, agents.rsu_range)],
        comm_ranges=np.full(n_cav + n_rsu, agents.comm_range),
    )
