"""``pose_spoof``: the attacker reports a world pose offset from its own estimate.

The lie is ``T_spoofed = T_reported * offset(t)``: ``offset`` is a translation of
``offset_m`` m in direction ``direction_deg`` of the attacker's frame (0 = forward, 90 =
left) and a rotation of ``offset_deg`` degrees (counter-clockwise), scaled by
``min(1, t / drift)`` (t: seconds since the episode's first frame), so with ``drift`` > 0
it grows slowly from nothing, under the radar of a check on jumps; ``drift = 0`` lies by
the full offset from the first step.

A victim moving the attacker's boxes with the spoofed pose misplaces them all by the
offset, and an aligner that matches them to the victim's own boxes finds the lie. With
``consistent: true`` the attacker forges the boxes of every object the victim also
detects (it knows what its victims see: the worst case) so that the lie moves them back
where they are, ``B' = offset^-1 * B``: matching confirms the lie, while the boxes of the
objects only the attacker sees stay in its true frame and land where the lie puts them.
(In a repetitive scene, a parking row, a spoof of exactly one pitch along the row needs
no forging at all: the shifted boxes land on the neighbouring objects.)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from roco_env.attacks.attack_stage import Attack, ObjectIds, StepContext, rewritten
from roco_env.geometry import se2_compose, se2_inverse, transform_boxes
from roco_env.scenario import ScenarioConfig
from roco_env.schema import build, spec
from roco_env.sensing.messages import Message

__all__ = ["PoseSpoof", "PoseSpoofParams", "offset_pose", "spoofed"]


@dataclass
class PoseSpoofParams:
    """``pose_spoof``: the lie about the attacker's pose and whether its boxes back it."""

    offset_m: float = spec(3.0, low=0.0, high=100.0, doc="translation of the lie, m")
    offset_deg: float = spec(0.0, low=-180.0, high=180.0,
                             doc="rotation of the lie, degrees (counter-clockwise)")
    direction_deg: float = spec(0.0, low=-180.0, high=180.0,
                                doc="direction of the translation in the attacker's frame, "
                                "degrees (0 forward, 90 left)")
    drift: float = spec(0.0, low=0.0, high=3600.0,
                        doc="seconds over which the offset grows linearly from zero to its "
                        "full value; 0 = the full offset from the first step")
    consistent: bool = spec(False, doc="forge the boxes of the objects a victim also detects "
                            "to agree with the lie")


def offset_pose(offset_m: float, direction_deg: float, offset_deg: float,
                fraction: float = 1.0) -> np.ndarray:
    """The SE(2) offset (3,) (x m, y m, yaw rad) in the attacker's frame: ``fraction`` of a
    translation of ``offset_m`` m towards ``direction_deg`` and a turn of ``offset_deg``."""
    heading = np.radians(direction_deg)
    return fraction * np.array([offset_m * np.cos(heading), offset_m * np.sin(heading),
                                np.radians(offset_deg)])


class PoseSpoof(Attack):
    """See the module docstring; parameters :class:`PoseSpoofParams`."""

    def __init__(self, config: ScenarioConfig, agent_ids: Sequence[str]) -> None:
        super().__init__(config, agent_ids)
        self.params = build(PoseSpoofParams, config.attack.params, "attack", "attack.params.")

    def offset(self, elapsed: float) -> np.ndarray:
        """The offset (3,) in the attacker's frame ``elapsed`` s into the episode."""
        p = self.params
        fraction = 1.0 if p.drift == 0.0 else min(1.0, elapsed / p.drift)
        return offset_pose(p.offset_m, p.direction_deg, p.offset_deg, fraction)

    def forge(self, step: StepContext, victim: int, attacker: int, message: Message,
              ids: ObjectIds) -> tuple[Message, ObjectIds]:
        return spoofed(step, victim, message, ids, self.offset(step.elapsed),
                       self.params.consistent)


def spoofed(step: StepContext, victim: int, message: Message, ids: ObjectIds,
            offset: np.ndarray, consistent: bool) -> tuple[Message, ObjectIds]:
    """``message`` reporting ``T_reported * offset`` (offset (3,) in the attacker's frame);
    with ``consistent`` the boxes of the objects ``victim`` also detects forged to agree."""
    boxes = message.boxes
    if consistent:
        seen = np.isin(ids, step.detections[victim].object_ids) & (ids >= 0)
        boxes = boxes.copy()
        boxes[seen] = transform_boxes(boxes[seen], se2_inverse(offset))
    return rewritten(message, ids, step.max_boxes,
                     pose=se2_compose(message.reported_pose, offset), boxes=boxes)
