"""Delay-aware alignment: a base aligner run on collaborators' boxes brought to the ego's time.

A late message (the network stage, roco_env.comm; docs/network.md) shows moving objects
where they were when its sender scanned; every box-matching aligner reads that
displacement as a pose error and "corrects" it. :class:`Compensate` tracks each
collaborator's boxes over its messages (:class:`roco_env.comm.tracking.BoxTracker`:
filterpy constant-velocity Kalman filters in the world frame, from the collaborator's
reported pose of each scan) and, before the base aligner runs:

* ``mode="extrapolate"`` (default): moves each box by its track's velocity times the
  message's age (``obs["collab_age"]``), into the sender's frame of the scan, so the
  boxes stand where their objects are now; boxes whose track has too few measurements
  to know a velocity stay where they are;
* ``mode="static"``: keeps only the boxes known to stand still (track speed below
  ``static_speed``), the collaborators' and the ego's own (its own boxes tracked the
  same way over its frames), which a delay cannot displace; the rest leave the
  observation's box masks.

The base aligner's action is the wrapper's; ``last_result`` is the base's (box indices
unchanged: boxes move or leave a mask, rows stay). Tracks are keyed by (ego,
collaborator) from ``info["agent"]`` / ``info["collaborators"]`` and reset with
:meth:`reset`; the ego's time is ``info["time"]``. Without the network stage (no
``collab_age`` in the observation) every message is of now and the base runs on the
observation as it is; with the env's own compensation (``comm.compensation: track``,
``info["compensated"]``) the boxes are of the ego's time already and extrapolate mode
leaves them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from roco_env.comm.tracking import KeyedTracks, TrackingParams, moved_boxes
from roco_env.policies.adapter import collaborator_keys
from roco_env.policies.base import AlignmentResult, Policy, policy_input_files
from roco_env.schema import build, spec

__all__ = ["Compensate", "CompensateParams"]

MODES = ("extrapolate", "static")


@dataclass(frozen=True)
class CompensateParams(TrackingParams):
    """The wrapper's own parameters (module docstring) and its tracks'."""

    base: str = spec("roco", doc="the policy run on the compensated observation")
    mode: str = spec("extrapolate", choices=MODES,
                     doc="extrapolate: boxes moved to the ego's time; static: only boxes "
                     "that stand still")
    static_speed: float = spec(0.5, low=0.0, high=10.0, low_open=True,
                               doc="static mode: the speed below which a box stands still, m/s")


class Compensate:
    """``Compensate(base="roco", **params)(obs, info) -> action (N, 3)``: the base aligner on
    delay-compensated boxes (module docstring). Parameters not of
    :class:`CompensateParams` go to the base policy."""

    keeps_state = "per ego and collaborator (info['agent'], info['collaborators'])"

    def __init__(self, **params: Any) -> None:
        own = {key: params.pop(key) for key in CompensateParams.__dataclass_fields__
               if key in params}
        self.params = build(CompensateParams, own, "compensate")
        from roco_env.policies import make_policy

        self.policy: Policy = make_policy(self.params.base, **params)
        self.tracks = KeyedTracks(self.params)

    @property
    def last_result(self) -> AlignmentResult | None:
        """The base policy's last AlignmentResult (None if it keeps none)."""
        return self.policy.last_result

    def input_files(self) -> tuple[Path, ...]:
        """The files the base policy declares, so a sweep's resume check covers them."""
        return policy_input_files(self.policy)

    def reset(self) -> None:
        """Forget every track (call between episodes) and reset the base policy."""
        self.tracks.reset()
        self.policy.reset()

    def __call__(self, observation: dict, info: dict | None = None) -> np.ndarray:
        if "collab_age" not in observation:
            return self.policy(observation, info)
        if info is None or "time" not in info:
            raise ValueError("compensate needs the env's info with 'time' (the network "
                             "stage's clock): call policy(obs[agent], infos[agent])")
        now = float(info["time"])
        filled = np.flatnonzero(np.asarray(observation["collab_mask"]) > 0)
        keys = collaborator_keys(info, filled, "compensate")
        obs = {**observation, "collab_boxes": np.array(observation["collab_boxes"]),
               "collab_box_mask": np.array(observation["collab_box_mask"]),
               "box_mask": np.array(observation["box_mask"])}
        compensated = bool(info.get("compensated"))  # the env moved them to now already
        extrapolate = self.params.mode == "extrapolate" and not compensated
        for slot, key in zip(filled.tolist(), keys, strict=True):
            rows = np.flatnonzero(obs["collab_box_mask"][slot] > 0)
            age = float(observation["collab_age"][slot])
            pose = np.asarray(observation["collab_poses"][slot], dtype=float)
            boxes = obs["collab_boxes"][slot, rows]
            velocity, known = self.tracks.velocities(key, boxes, pose,
                                                     now if compensated else now - age,
                                                     bool(observation["collab_new"][slot]))
            if extrapolate:
                obs["collab_boxes"][slot, rows] = moved_boxes(boxes, pose, velocity, age)
            elif self.params.mode == "static":
                obs["collab_box_mask"][slot, rows] = self._standing(velocity, known)
        if self.params.mode == "static":
            rows = np.flatnonzero(obs["box_mask"] > 0)
            obs["box_mask"][rows] = self._standing(*self.tracks.velocities(
                (info["agent"], info["agent"]), np.asarray(observation["boxes"])[rows],
                np.asarray(observation["pose"], dtype=float), now, True))
        return self.policy(obs, info)

    def _standing(self, velocity: np.ndarray, known: np.ndarray) -> np.ndarray:
        """int8 mask: 1 where a box's track is known to move slower than static_speed."""
        return (known & (np.hypot(*velocity.T) < self.params.static_speed)).astype(np.int8)
