"""The learned attackers as PettingZoo agents: a ParallelEnv of every agent of a
:class:`~roco_env.env.CollabPerceptionEnv` plus ``attacker_0``, ``attacker_1``, ...

``AdversarialEnv(roco_env.parallel_env(scenario, **{"attack.kind": "learned", ...}))``.
The vehicles and RSUs stay the env's egos, with their observations, actions and rewards
unchanged (an attacking vehicle still fuses for itself); who attacks is still drawn per
episode and never reaches their observations. ``attacker_k`` controls the lie of the
k-th attacker of the episode (:mod:`roco_env.attacks.learned_attack`):

* observation: what its vehicle observes as an ego (the env's observation of that
  agent, same space as every ego's);
* action: its Box of pose offset and ghosts, applied to the messages of the next frame;
* reward: minus its victims' AP@0.7 (or its target's), minus its detection penalty;
* info: ``{"agent": "attacker_k", "privileged": {"vehicle": the agent it attacks as}}``.

Terminations and truncations are the env's (every agent ends together).
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from typing import Any

import gymnasium
import numpy as np
from pettingzoo import ParallelEnv

from roco_env.attacks.learned_attack import LearnedAttack
from roco_env.env import CollabPerceptionEnv

__all__ = ["AdversarialEnv", "attacker_ids"]


def attacker_ids(count: int) -> list[str]:
    """The attacker agents' ids."""
    return [f"attacker_{k}" for k in range(count)]


class AdversarialEnv(ParallelEnv):
    """See the module docstring. ``env``: a CollabPerceptionEnv with ``attack.kind:
    learned`` whose infos carry the APs (``info_level`` full or metrics)."""

    def __init__(self, env: CollabPerceptionEnv) -> None:
        attack = getattr(getattr(env, "pipeline", None), "attack", None)
        if not isinstance(attack, LearnedAttack):
            raise ValueError("AdversarialEnv needs a CollabPerceptionEnv with attack.kind="
                             f"'learned'; got {type(attack).__name__ if attack else env!r}")
        if env.info_level == "none":
            raise ValueError("AdversarialEnv needs the APs in the infos: info_level 'full' or "
                             "'metrics', not 'none'")
        self.env, self.attack = env, attack
        self.attackers = attacker_ids(attack.n_attackers)
        self.possible_agents = list(env.possible_agents) + self.attackers
        self.agents: list[str] = []
        self.metadata = env.metadata
        self.render_mode = env.render_mode
        seen = env.observation_space(env.possible_agents[0])
        self._spaces = {a: (copy.deepcopy(seen), attack.action_space()) for a in self.attackers}

    def observation_space(self, agent: str) -> gymnasium.spaces.Space:
        if agent in self._spaces:
            return self._spaces[agent][0]
        return self.env.observation_space(agent)

    def action_space(self, agent: str) -> gymnasium.spaces.Space:
        if agent in self._spaces:
            return self._spaces[agent][1]
        return self.env.action_space(agent)

    def vehicle(self, index: int) -> str:
        """The agent the ``index``-th attacker attacks as in this episode."""
        return self.env.possible_agents[self.attack.attackers[index]]

    def reset(self, seed: int | None = None,
              options: dict | None = None) -> tuple[dict[str, Any], dict[str, dict]]:
        observations, infos = self.env.reset(seed=seed, options=options)
        self.agents = list(self.possible_agents)
        return self._with_attackers(observations, infos)

    def step(self, actions: Mapping[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        missing = [a for a in self.attackers if a not in actions]
        if self.agents and missing:
            raise ValueError(f"actions is missing attacker(s) {missing}")
        for index, agent in enumerate(self.attackers):
            if agent in self.agents:
                self.attack.act(index, actions[agent])
        observations, rewards, terminations, truncations, infos = self.env.step(
            {a: action for a, action in actions.items() if a not in self._spaces})
        observations, infos = self._with_attackers(observations, infos)
        for index, agent in enumerate(self.attackers):
            rewards[agent] = self.attack.reward(index, infos)
            terminations[agent] = any(terminations.values())
            truncations[agent] = any(truncations.values())
        self.agents = [] if not self.env.agents else list(self.possible_agents)
        return observations, rewards, terminations, truncations, infos

    def _with_attackers(self, observations: dict, infos: dict) -> tuple[dict, dict]:
        for index, agent in enumerate(self.attackers):
            vehicle = self.vehicle(index)
            observations[agent] = copy.deepcopy(observations[vehicle])
            infos[agent] = {"agent": agent, "privileged": {"vehicle": vehicle}}
        return observations, infos

    def render(self) -> np.ndarray | None:
        return self.env.render()

    def close(self) -> None:
        self.env.close()

    def state(self) -> np.ndarray:
        return self.env.state()
