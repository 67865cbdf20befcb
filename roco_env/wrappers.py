"""Views of the environment for other libraries.

* :class:`EgoEnv`: a single-agent ``gymnasium.Env`` controlling one agent's
  corrections while every other agent acts with a given policy (default
  identity). Also registered as ``roco/CollabPerceptionEgo-v0`` in Gymnasium.
* :class:`FlattenObservations`: a PettingZoo parallel wrapper turning each
  agent's Dict observation into one flat float32 Box (``gymnasium.spaces.flatten``),
  which SuperSuit's Box-only wrappers (``pad_observations_v0``, ``flatten_v0``)
  and most RL libraries need.
* :class:`FlattenActions`: a PettingZoo parallel wrapper exposing each agent's
  (N, 3) correction as a flat (3N,) Box, for libraries whose action
  distributions need one-dimensional actions (RLlib's PPO).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv
from pettingzoo.utils import BaseParallelWrapper

from roco_env.action_modes import ActionMode
from roco_env.env import DEFAULT_MAX_CYCLES, DEFAULT_SCENARIO, CollabPerceptionEnv
from roco_env.policies import make_policy
from roco_env.policies.base import Policy, StatelessPolicy, as_policy
from roco_env.policies.spec import merge_env_overrides
from roco_env.scenario import ScenarioConfig


class EgoEnv(gymnasium.Env):
    """One agent of :class:`CollabPerceptionEnv` as a Gymnasium env.

    env: an existing (unwrapped) parallel env, or None to build one from
    ``scenario``, ``max_cycles``, ``render_mode``, ``info_level``, ``privileged`` and
    ``overrides``; agent: the controlled agent (default: the first evaluated agent);
    others: the policy ``policy(obs, info) -> action`` of every other agent (one instance
    serves them all; a :class:`~roco_env.policies.base.Policy`, or any callable), or a
    policy name for :func:`roco_env.policies.make_policy` (``"roco"``); by default they take
    the action mode's neutral action (zeros: trust the reported poses in ``correction``
    mode, keep the base aligner's poses in ``residual`` and ``gate`` modes, the first
    choice in ``select`` mode). A built env takes the env modes the others' policy
    declares in its ``env_overrides`` (``others="learned_select"`` builds a select-mode
    env; a conflicting override is a ValueError naming the field). A built env scores only the controlled agent (the others
    act unscored) unless ``evaluate_others`` is True; an env passed in is used as it is.
    Observation, action, reward and info are that agent's (see roco_env.env).
    Infos have fixed shapes and no NaN (see roco_env.env), so Gymnasium's vector
    envs (``gymnasium.make_vec(..., vectorization_mode="sync" | "async")``) stack
    them and its determinism check compares them.
    """

    # Class-level, as gymnasium.make reads the render modes from the class before building
    # (an instance-only metadata made it warn that every render_mode was unsupported);
    # an instance's render_fps follows its scenario's time step, as the parallel env's.
    metadata = {"render_modes": list(CollabPerceptionEnv.metadata["render_modes"]),
                "render_fps": CollabPerceptionEnv.metadata["render_fps"]}

    def __init__(self, scenario: str | os.PathLike | ScenarioConfig = DEFAULT_SCENARIO,
                 max_cycles: int = DEFAULT_MAX_CYCLES, render_mode: str | None = None, *,
                 env: CollabPerceptionEnv | None = None, agent: str | None = None,
                 others: Callable | str | None = None, info_level: str = "full",
                 privileged: bool | None = None, evaluate_others: bool = False,
                 **overrides: Any) -> None:
        built = env is None
        if isinstance(others, str):
            others = make_policy(others)
        if built:  # in the env modes the others' policy acts in (a learned policy's)
            overrides = merge_env_overrides(overrides, others, "others")
        self.env = CollabPerceptionEnv(
            scenario, max_cycles=max_cycles, render_mode=render_mode, info_level=info_level,
            privileged=privileged, **overrides) if built else env
        if not isinstance(self.env, CollabPerceptionEnv):
            raise ValueError(f"env must be an unwrapped CollabPerceptionEnv; "
                             f"got {type(self.env).__name__}")
        base = self.env
        self.agent = agent if agent is not None else base.evaluated_agents[0]
        if self.agent not in base.possible_agents:
            raise ValueError(f"agent must be one of {base.possible_agents}; got {self.agent!r}")
        if built and not evaluate_others:  # fuse and score only what this env returns
            base.evaluated_agents = [self.agent]
        base.render_ego = self.agent  # pictures show the controlled agent's fused view
        self.others: Policy = as_policy(others, "others") if others is not None \
            else _NeutralPolicy(base.action_mode)
        self.observation_space = base.observation_space(self.agent)
        self.action_space = base.action_space(self.agent)
        self.metadata = {**type(self).metadata, "render_fps": base.metadata["render_fps"]}
        self.render_mode = base.render_mode
        self._last: tuple[dict, dict] | None = None

    def reset(self, *, seed: int | None = None,
              options: dict | None = None) -> tuple[dict, dict]:
        super().reset(seed=seed)
        self.others.reset()  # a stateful policy starts each episode afresh
        observations, infos = self.env.reset(seed=seed, options=options)
        self._last = (observations, infos)
        return observations[self.agent], infos[self.agent]

    def step(self, action: np.ndarray) -> tuple[dict, float, bool, bool, dict]:
        if self._last is None:
            raise ValueError("step() called before reset()")
        observations, infos = self._last
        actions = {a: self.others(observations[a], infos[a])
                   for a in self.env.agents if a != self.agent}
        actions[self.agent] = action
        observations, rewards, terminations, truncations, infos = self.env.step(actions)
        self._last = (observations, infos)
        return (observations[self.agent], float(rewards[self.agent]),
                bool(terminations[self.agent]), bool(truncations[self.agent]), infos[self.agent])

    def render(self) -> np.ndarray | None:
        return self.env.render()

    def close(self) -> None:
        self.env.close()


class _NeutralPolicy(StatelessPolicy):
    """Takes the action mode's neutral action whatever it observes."""

    def __init__(self, mode: ActionMode) -> None:
        self.mode = mode

    def __call__(self, observation: dict, info: dict | None = None) -> np.ndarray:
        return self.mode.neutral_action()


class FlattenObservations(BaseParallelWrapper):
    """Each agent's Dict observation flattened into one float32 Box (keys in space order)."""

    def __init__(self, env: ParallelEnv) -> None:
        super().__init__(env)
        self._dict_spaces = {a: env.observation_space(a) for a in env.possible_agents}
        self._flat_spaces = {a: spaces.flatten_space(space)
                             for a, space in self._dict_spaces.items()}

    def observation_space(self, agent: str) -> spaces.Box:
        return self._flat_spaces[agent]

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        observations, infos = self.env.reset(seed=seed, options=options)
        return self._flatten(observations), infos

    def step(self, actions: dict) -> tuple[dict, dict, dict, dict, dict]:
        observations, rewards, terminations, truncations, infos = self.env.step(actions)
        return self._flatten(observations), rewards, terminations, truncations, infos

    def _flatten(self, observations: dict) -> dict:
        return {a: spaces.flatten(self._dict_spaces[a], obs) for a, obs in observations.items()}


class FlattenActions(BaseParallelWrapper):
    """Each agent's (N, 3) correction action exposed as a flat (3N,) float32 Box.

    Flat actions are reshaped to (N, 3) (slot-major: dx, dy, dyaw per slot)
    before they reach the environment, which still validates them.
    """

    def __init__(self, env: ParallelEnv) -> None:
        super().__init__(env)
        for agent in env.possible_agents:
            if not isinstance(env.action_space(agent), spaces.Box):
                raise ValueError(
                    f"FlattenActions flattens Box actions (action.mode correction or residual); "
                    f"{agent!r} has {env.action_space(agent)}: RL libraries take MultiDiscrete "
                    "actions (select and gate modes) as they are")
        self._shapes = {a: env.action_space(a).shape for a in env.possible_agents}
        self._flat_spaces = {}
        for agent in env.possible_agents:
            box = env.action_space(agent)
            self._flat_spaces[agent] = spaces.Box(box.low.reshape(-1), box.high.reshape(-1),
                                                  dtype=box.dtype)

    def action_space(self, agent: str) -> spaces.Box:
        return self._flat_spaces[agent]

    def step(self, actions: dict) -> tuple[dict, dict, dict, dict, dict]:
        return self.env.step({a: self._unflatten(a, act) for a, act in actions.items()})

    def _unflatten(self, agent: str, action: Any) -> Any:
        if agent not in self._shapes:
            return action  # the env names the unknown agent
        action = np.asarray(action)
        expected = self._flat_spaces[agent].shape
        if action.shape != expected:
            raise ValueError(f"action of {agent!r} must have shape {expected} "
                             f"(flattened (N, 3) corrections); got {action.shape}")
        return action.reshape(self._shapes[agent])
