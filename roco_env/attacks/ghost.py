"""``ghost``: the attacker injects ``n_ghost`` fake car boxes into what it sends.

Placements (``placement``), every ghost a car-sized box (:data:`GHOST_SIZE`) with score
``score`` and the median uncertainty of the attacker's real boxes:

* ``random``: positions drawn once per episode (from the attack's stream) in the
  attacker's frame, uniform over the ring 5 m .. ``spread_m`` m around it, headings
  uniform; they travel with the attacker.
* ``lanes``: each ghost follows one of the attacker's real boxes (highest score first,
  cycling), ``gap_m`` m bumper to bumper ahead of it along its heading (the next ghost
  on that box one car further), so ghosts lie in the lanes traffic uses. No real box,
  no ghost.
* ``aliasing``: copies of the victim's own boxes (its ``n_ghost`` highest-scoring ones),
  placed in the attacker's frame so that the correction ``delta`` (``shift_m`` m towards
  ``direction_deg`` and ``shift_deg`` degrees, in the victim's frame) lays them exactly on
  the victim's boxes: ``G = T_rel^-1 * delta^-1 * E`` with ``T_rel`` the attacker's
  reported pose seen from the victim. The attacker withholds its own boxes of the objects
  the victim also detects (they would support the true pose), so an aligner matching
  boxes finds ``delta`` the only well-supported correction and moves every real box of
  the attacker by it.

Injected boxes carry object id -1 (privileged); a message keeps at most K boxes, its
highest-scoring ones.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from roco_env.attacks.attack_stage import Attack, ObjectIds, StepContext, rewritten
from roco_env.attacks.pose import offset_pose
from roco_env.geometry import se2_compose, se2_inverse, se2_relative, transform_boxes
from roco_env.observation import top_k
from roco_env.scenario import ScenarioConfig
from roco_env.schema import build, spec
from roco_env.sensing.messages import Message

__all__ = ["GHOST_SIZE", "Ghost", "GhostParams", "car_boxes", "with_ghosts"]

GHOST_SIZE = (4.5, 1.9, 1.6)  # length, width, height of a random or lane ghost, m
_FALLBACK_UNCERTAINTY = (0.1, 0.1, 0.03)  # sigma_x m, sigma_y m, sigma_yaw rad without real boxes
_NEAREST_M = 5.0  # random ghosts keep this far from the attacker's sensor, m


@dataclass
class GhostParams:
    """``ghost``: how many fake boxes and where."""

    n_ghost: int = spec(5, low=0, high=1024, doc="fake boxes per message")
    placement: str = spec("random", choices=("random", "lanes", "aliasing"),
                          doc="random: anywhere near the attacker; lanes: ahead of the "
                          "vehicles it sees; aliasing: copies of the victim's boxes that make "
                          "a wrong pose hypothesis win")
    spread_m: float = spec(40.0, low=_NEAREST_M, high=300.0,
                           doc="random: the farthest a ghost lies from the attacker, m")
    gap_m: float = spec(3.0, low=0.0, high=50.0,
                        doc="lanes: bumper gap between a real vehicle and its ghost, m")
    shift_m: float = spec(3.0, low=0.0, high=100.0,
                          doc="aliasing: translation of the wrong hypothesis, m")
    shift_deg: float = spec(0.0, low=-180.0, high=180.0,
                            doc="aliasing: rotation of the wrong hypothesis, degrees")
    direction_deg: float = spec(0.0, low=-180.0, high=180.0,
                                doc="aliasing: direction of its translation in the victim's "
                                "frame, degrees (0 forward, 90 left)")
    score: float = spec(0.9, low=0.0, high=1.0, low_open=True, doc="the ghosts' score")


class Ghost(Attack):
    """See the module docstring; parameters :class:`GhostParams`."""

    def __init__(self, config: ScenarioConfig, agent_ids: Sequence[str]) -> None:
        super().__init__(config, agent_ids)
        self.params = build(GhostParams, config.attack.params, "attack", "attack.params.")
        self._random: dict[int, np.ndarray] = {}

    def start(self, rng: np.random.Generator) -> None:
        """``random``: each attacker's ghost poses (n_ghost, 3) in its frame."""
        n, far = self.params.n_ghost, self.params.spread_m
        self._random = {}
        if self.params.placement != "random":
            return
        for attacker in self.attackers:
            radius = np.sqrt(rng.uniform(_NEAREST_M**2, far**2, n))
            bearing, heading = rng.uniform(-np.pi, np.pi, (2, n))
            self._random[attacker] = np.stack(
                [radius * np.cos(bearing), radius * np.sin(bearing), heading], axis=1)

    def ghosts(self, step: StepContext, victim: int, attacker: int,
               message: Message) -> np.ndarray:
        """The ghost boxes (G, 7) in the attacker's frame for this message."""
        placement = self.params.placement
        if placement == "aliasing":
            mine = step.detections[victim]
            chosen = top_k(mine.scores, self.params.n_ghost)
            p = self.params
            delta = offset_pose(p.shift_m, p.direction_deg, p.shift_deg)
            seen_from_victim = se2_relative(step.own[victim], message.reported_pose)
            return transform_boxes(mine.boxes[chosen],
                                   se2_compose(se2_inverse(seen_from_victim), se2_inverse(delta)))
        if placement == "random":
            return car_boxes(self._random[attacker])
        return car_boxes(_ahead(message.boxes, message.scores, self.params.n_ghost,
                                 self.params.gap_m))

    def forge(self, step: StepContext, victim: int, attacker: int, message: Message,
              ids: ObjectIds) -> tuple[Message, ObjectIds]:
        real = np.ones(ids.shape[0], dtype=bool)
        if self.params.placement == "aliasing":  # the true pose's support withheld
            real = ~(np.isin(ids, step.detections[victim].object_ids) & (ids >= 0))
        return with_ghosts(message, ids, self.ghosts(step, victim, attacker, message),
                           self.params.score, step.max_boxes, real)


def with_ghosts(message: Message, ids: ObjectIds, ghosts: np.ndarray, score: float,
                max_boxes: int, real: np.ndarray | None = None) -> tuple[Message, ObjectIds]:
    """``message`` with its ``real`` boxes (bool; default all) and the ``ghosts`` (G, 7)
    appended (score ``score``, the real boxes' median uncertainty, object id -1), then its
    ``max_boxes`` highest-scoring boxes."""
    count = ghosts.shape[0]
    real = np.ones(ids.shape[0], dtype=bool) if real is None else real
    typical = np.median(message.uncertainty, axis=0) if message.scores.shape[0] \
        else np.array(_FALLBACK_UNCERTAINTY)
    return rewritten(
        message, np.concatenate([ids, np.full(count, -1, dtype=np.int64)]), max_boxes,
        boxes=np.concatenate([message.boxes, ghosts]),
        uncertainty=np.concatenate([message.uncertainty, np.tile(typical, (count, 1))]),
        scores=np.concatenate([message.scores, np.full(count, score)]),
        keep=np.concatenate([real, np.ones(count, dtype=bool)]))


def _ahead(boxes: np.ndarray, scores: np.ndarray, count: int, gap: float) -> np.ndarray:
    """(G, 3) poses of ``count`` ghosts in lanes: ghost g follows real box g mod R (by
    descending score), (g // R + 1) cars of its length plus ``gap`` ahead of it; none
    without real boxes."""
    if boxes.shape[0] == 0:
        return np.zeros((0, 3))
    order = np.argsort(-scores, kind="stable")
    g = np.arange(count)
    base = boxes[order[g % order.shape[0]]]
    reach = (g // order.shape[0] + 1) * (0.5 * base[:, 3] + gap + 0.5 * GHOST_SIZE[0])
    return np.stack([base[:, 0] + reach * np.cos(base[:, 6]),
                     base[:, 1] + reach * np.sin(base[:, 6]), base[:, 6]], axis=1)


def car_boxes(poses: np.ndarray) -> np.ndarray:
    """Car-sized boxes (G, 7) at poses (G, 3) (x m, y m, yaw rad), standing on the ground."""
    length, width, height = GHOST_SIZE
    count = poses.shape[0]
    return np.column_stack([poses[:, 0], poses[:, 1], np.full(count, 0.5 * height),
                            np.full(count, length), np.full(count, width),
                            np.full(count, height), poses[:, 2]])
