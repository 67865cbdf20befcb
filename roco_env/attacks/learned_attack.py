"""``learned``: the attackers' lies come from actions, each attacker a PettingZoo agent.

The attack stage holds one action per attacker (set by :meth:`LearnedAttack.act`; zeros,
no lie, after ``reset``) and applies it to every message that attacker sends a victim
from the next frame on (the views of a frame are built when the env advances to it, so
an action taken on frame t shapes frame t + 1). An action is a Box in [-1, 1] of
``3 + 3 * ghosts`` values (:meth:`LearnedAttack.action_space`):

* ``(dx, dy, dyaw)``: the pose offset, ``budget_m`` m x (dx, dy) (the translation clipped
  to a disc of radius ``budget_m``) and ``budget_deg`` degrees x dyaw, in the attacker's
  frame, reported as ``T_reported * offset``; with ``consistent`` the boxes of the objects
  a victim also detects are forged to agree (as ``pose_spoof``);
* per ghost ``(x, y, on)``: a car-sized ghost at ``ghost_range_m`` m x (x, y) in the
  attacker's frame, heading along its x axis, injected when ``on > 0``.

The reward of an attacker (:meth:`LearnedAttack.reward`) is minus the victims' mean
per-step AP@0.7 (the honest evaluated agents; ``target``: that agent's alone; an undefined
AP counts as 0) minus ``detection_penalty`` x the share of its victims that rejected it
this step, so an attacker that gets itself rejected (which costs the victims only its
contribution) is not paid for it. :class:`roco_env.attacks.adversarial_env.AdversarialEnv`
makes the attackers agents of the env.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from gymnasium import spaces

from roco_env.attacks.attack_stage import Attack, ObjectIds, StepContext
from roco_env.attacks.ghost import car_boxes, with_ghosts
from roco_env.attacks.pose import spoofed
from roco_env.scenario import ScenarioConfig
from roco_env.schema import ConfigError, build, spec
from roco_env.sensing.messages import Message

__all__ = ["LearnedAttack", "LearnedAttackParams"]

GHOST_SCORE = 0.9  # the score a learned ghost is sent with


@dataclass
class LearnedAttackParams:
    """``learned``: the budget of the attackers' actions and their reward."""

    budget_m: float = spec(3.0, low=0.0, high=100.0,
                           doc="the largest pose translation an attacker may report, m")
    budget_deg: float = spec(3.0, low=0.0, high=180.0,
                             doc="the largest pose rotation an attacker may report, degrees")
    ghosts: int = spec(5, low=0, high=64, doc="ghost boxes an attacker may inject per message")
    ghost_range_m: float = spec(40.0, low=1.0, high=300.0,
                                doc="how far from the attacker a ghost may lie, m (per axis)")
    consistent: bool = spec(True, doc="forge the boxes of the objects a victim also detects "
                            "to agree with the lie")
    target: str | None = spec(None, doc="the agent whose AP@0.7 the reward is minus; null = "
                              "the mean over the attacker's victims")
    detection_penalty: float = spec(1.0, low=0.0, high=100.0,
                                    doc="reward lost when every victim rejects the attacker")


class LearnedAttack(Attack):
    """See the module docstring; parameters :class:`LearnedAttackParams`."""

    def __init__(self, config: ScenarioConfig, agent_ids: Sequence[str]) -> None:
        super().__init__(config, agent_ids)
        self.params = build(LearnedAttackParams, config.attack.params, "attack",
                            "attack.params.")
        target = self.params.target
        if target is not None and (target not in self.agent_ids or target in config.attack.agents):
            raise ConfigError(f"attack: attack.params.target={target!r} must be an honest "
                              f"agent; choose among {list(self.agent_ids)} (not an attacker)")
        self.size = 3 + 3 * self.params.ghosts
        self._actions = np.zeros((self.n_attackers, self.size))

    def action_space(self) -> spaces.Box:
        """One attacker's action space (module docstring)."""
        return spaces.Box(-1.0, 1.0, (self.size,), np.float32)

    def start(self, rng: np.random.Generator) -> None:
        """No lie until the first action."""
        self._actions[:] = 0.0

    def act(self, index: int, action: object) -> None:
        """Set the ``index``-th attacker's action (of this episode's attackers, in order) for
        the frames to come; clipped to [-1, 1]. A wrong shape or a non-finite value is a
        ValueError naming the attacker."""
        array = np.asarray(action, dtype=float)
        if array.shape != (self.size,) or not np.all(np.isfinite(array)):
            raise ValueError(f"action of attacker_{index} must be {self.size} finite numbers "
                             f"in [-1, 1] (dx, dy, dyaw, then x, y, on per ghost); got "
                             f"{np.asarray(action)!r}")
        self._actions[index] = np.clip(array, -1.0, 1.0)

    def offset(self, index: int) -> np.ndarray:
        """The ``index``-th attacker's pose offset (3,) (x m, y m, yaw rad), its frame."""
        shift = self._actions[index, :2] * self.params.budget_m
        reach = np.hypot(*shift)
        if reach > self.params.budget_m:
            shift *= self.params.budget_m / reach
        return np.array([shift[0], shift[1], np.radians(self._actions[index, 2]
                                                        * self.params.budget_deg)])

    def forge(self, step: StepContext, victim: int, attacker: int, message: Message,
              ids: ObjectIds) -> tuple[Message, ObjectIds]:
        index = self.attackers.index(attacker)
        message, ids = spoofed(step, victim, message, ids, self.offset(index),
                               self.params.consistent)
        ghosts = self._actions[index, 3:].reshape(-1, 3)
        placed = ghosts[ghosts[:, 2] > 0.0]
        poses = np.column_stack([placed[:, :2] * self.params.ghost_range_m,
                                 np.zeros(placed.shape[0])])
        return with_ghosts(message, ids, car_boxes(poses), GHOST_SCORE, step.max_boxes)

    def reward(self, index: int, infos: Mapping[str, Mapping]) -> float:
        """The ``index``-th attacker's reward for a step whose infos (by agent id, with the
        APs, ``rejected`` and ``evaluated_collaborators``) are ``infos`` (module docstring)."""
        me = self.agent_ids[self.attackers[index]]
        attackers = {self.agent_ids[k] for k in self.attackers}
        victims = [a for a, info in infos.items() if a not in attackers and "ap70" in info]
        scored = [self.params.target] if self.params.target is not None else victims
        ap = np.mean([max(float(infos[a]["ap70"]), 0.0) for a in scored]) if scored else 0.0
        caught = [bool(infos[a]["rejected"][slot]) for a in victims
                  for slot, sender in enumerate(infos[a]["evaluated_collaborators"])
                  if sender == me]
        return float(-ap - self.params.detection_penalty * (np.mean(caught) if caught else 0.0))
