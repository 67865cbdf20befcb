"""Compiled (numba) loops of RoCo's map: the new landmarks of an accepted collaborator
and the map after its commit (tests/test_matching_kernels.py checks them against the
array path). The matching's own loops (the gate search, the edge similarity, the
assignment's index compaction) live in :mod:`roco_env.policies.pose_kernels`, next to
the solver that RoCo's compiled matching rounds call with them: a compiled function
calls only functions of its own module, because numba's on-disk cache notices edits to
a function's own file only. The map's records, which the compiled commit builds, are
defined here (:class:`LandmarkMap`, :class:`Observations`); a collaborator's boxes are a
:class:`~roco_env.policies.pose_kernels.AgentBoxes`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

__all__ = ["LandmarkMap", "Observations", "committed_map", "placed_landmarks"]


class LandmarkMap(NamedTuple):
    """RoCo's landmarks: poses (L, 3) in the ego frame, pose features (5, L)
    (``matching.pose_features``) and the covariance (L, 3, 3) of the box that created
    each."""

    poses: np.ndarray
    features: np.ndarray
    covariance: np.ndarray


class Observations(NamedTuple):
    """RoCo's observations (O,): observation o is box ``box[o]`` of agent ``agent[o]``
    (0 = the ego) seeing landmark ``land[o]``."""

    agent: np.ndarray
    box: np.ndarray
    land: np.ndarray


@njit(cache=True)
def placed_landmarks(pose, own, boxes):
    """The agent's boxes ``own[boxes]`` (own (K, 3) in its frame, boxes (B,) indices) placed
    in the ego frame by its pose (3,) as ``geometry.se2_compose(pose, own[boxes])`` does
    (yaw wrapped to (-pi, pi]), with their pose features (5, B) (``matching.pose_features``:
    x, y, x^2 + y^2, cos(yaw), sin(yaw))."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    poses = np.empty((boxes.size, 3))
    features = np.empty((5, boxes.size))
    for k in range(boxes.size):
        bx, by, byaw = own[boxes[k], 0], own[boxes[k], 1], own[boxes[k], 2]
        x = pose[0] + c * bx - s * by
        y = pose[1] + s * bx + c * by
        yaw = (pose[2] + byaw + math.pi) % (2.0 * math.pi) - math.pi
        if yaw <= -math.pi:
            yaw += 2.0 * math.pi
        poses[k, 0], poses[k, 1], poses[k, 2] = x, y, yaw
        features[0, k], features[1, k], features[2, k] = x, y, x * x + y * y
        features[3, k], features[4, k] = math.cos(yaw), math.sin(yaw)
    return poses, features


@njit(cache=True)
def committed_map(pose, match_land, match_box, boxes, agent, landmarks, observations):
    """RoCo's map after accepting a collaborator (``roco._commit``), in one pass: its
    boxes (:class:`~roco_env.policies.pose_kernels.AgentBoxes`: poses (K, 3) in its frame,
    covariance (K, 3, 3)) matched as match_box (P,) to the landmarks match_land (P,)
    become observations, the unmatched ones (in increasing box order) new landmarks placed
    by its pose (3,) (:func:`placed_landmarks`). Returns the :class:`LandmarkMap` (M')
    and the :class:`Observations` (O'): the inputs with the new rows appended, as
    ``np.concatenate`` gives them (agent: the collaborator's index)."""
    own, covariance = boxes.poses, boxes.covariance
    land_poses, land_features = landmarks.poses, landmarks.features
    land_covariance = landmarks.covariance
    obs_agent, obs_box, obs_land = observations.agent, observations.box, observations.land
    unmatched = np.ones(own.shape[0], dtype=np.bool_)
    for k in range(match_box.size):
        unmatched[match_box[k]] = False
    new_boxes = np.nonzero(unmatched)[0]
    n_land, n_new, n_obs = land_poses.shape[0], new_boxes.size, obs_agent.size
    new_poses, new_features = placed_landmarks(pose, own, new_boxes)
    poses = np.concatenate((land_poses, new_poses))
    features = np.empty((5, n_land + n_new))
    features[:, :n_land] = land_features
    features[:, n_land:] = new_features
    land_cov = np.empty((n_land + n_new, 3, 3))
    land_cov[:n_land] = land_covariance
    for k in range(n_new):
        land_cov[n_land + k] = covariance[new_boxes[k]]
    size = n_obs + own.shape[0]
    agents, box_ids = np.empty(size, np.int64), np.empty(size, np.int64)
    lands = np.empty(size, np.int64)
    agents[:n_obs], box_ids[:n_obs], lands[:n_obs] = obs_agent, obs_box, obs_land
    agents[n_obs:] = agent
    for k in range(match_box.size):
        box_ids[n_obs + k], lands[n_obs + k] = match_box[k], match_land[k]
    for k in range(n_new):
        box_ids[n_obs + match_box.size + k] = new_boxes[k]
        lands[n_obs + match_box.size + k] = n_land + k
    return LandmarkMap(poses, features, land_cov), Observations(agents, box_ids, lands)
