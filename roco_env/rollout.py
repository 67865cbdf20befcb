"""The episode loop: one policy per agent acting in a :class:`~roco_env.env.CollabPerceptionEnv`.

:func:`play_episode` is the package's one loop of policies over a parallel env: the sweeps
(and through them ``roco-env run``/``render`` and the stress search) and the env-step and
alignment benchmarks run it. The policies start a new episode (``reset``), the env resets
with the seed, then every step each live agent's policy acts on the observation and info it
was given, the env checks the actions (its action mode's check, the only one) and steps.
Each step is yielded as a :class:`Step`: every agent's :class:`Turn` (what its policy
saw, the action as the policy returned it, the alignment result of that very call, the
call's wall time) and what ``env.step`` returned. Loops without policies step the env
themselves with zero actions: the detector assessment's episodes
(:mod:`roco_env.training.assessment`, which read the env's state before each step) and
the learned detector's step-rate benchmark (:mod:`roco_env.benchmarks.learned_detector`,
which times ``env.step`` alone).
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from roco_env.policies.base import AlignmentResult, act, as_policy

if TYPE_CHECKING:
    from roco_env.env import CollabPerceptionEnv


@dataclass(frozen=True)
class Turn:
    """One agent's policy call in one step.

    observation, info: what the env returned to the agent (the policy's input);
    action: the action as the policy returned it (``env.step`` checked it);
    result: the policy's :class:`~roco_env.policies.base.AlignmentResult` of this call,
    None when it reported none; seconds: wall time of the call (s, not reproducible).
    """

    observation: dict
    info: dict
    action: Any
    result: AlignmentResult | None
    seconds: float


@dataclass(frozen=True)
class Step:
    """One env step: ``number`` (from 1), the agents' turns, and the observations,
    rewards, terminations, truncations and infos ``env.step`` returned."""

    number: int
    turns: dict[str, Turn]
    observations: dict[str, dict]
    rewards: dict[str, float]
    terminations: dict[str, bool]
    truncations: dict[str, bool]
    infos: dict[str, dict]

    @property
    def actions(self) -> dict[str, Any]:
        """The actions of the step by agent, as the policies returned them."""
        return {agent: turn.action for agent, turn in self.turns.items()}


def play_episode(env: CollabPerceptionEnv, policies: Mapping[str, Any],
                 seed: int | None = None, max_steps: int | None = None) -> Iterator[Step]:
    """Play one episode of ``env`` from ``env.reset(seed=seed)``, yielding every step.

    policies: agent id -> its policy (a :class:`~roco_env.policies.base.Policy` or any
    callable ``policy(obs, info) -> action``; one instance may serve several agents), for
    every agent of ``env.possible_agents``. The episode ends when the env truncates it
    or after ``max_steps`` steps (None: no limit of its own). A missing policy is a
    ValueError naming the agents; a bad action is the env's ValueError naming the agent.
    """
    missing = [agent for agent in env.possible_agents if agent not in policies]
    if missing:
        raise ValueError(f"policies lacks agent(s) {missing}; give a policy for every agent "
                         f"of env.possible_agents {env.possible_agents}")
    adapted = {id(policy): as_policy(policy, f"the policy of {agent!r}")
               for agent, policy in policies.items()}
    for policy in adapted.values():
        policy.reset()
    chosen = {agent: adapted[id(policy)] for agent, policy in policies.items()}
    observations, infos = env.reset(seed=seed)
    number = 0
    while env.agents and (max_steps is None or number < max_steps):
        turns = {}
        for agent in env.agents:
            start = time.perf_counter()
            action, result = act(chosen[agent], observations[agent], infos[agent])
            turns[agent] = Turn(observations[agent], infos[agent], action, result,
                                time.perf_counter() - start)
        observations, rewards, terminations, truncations, infos = env.step(
            {agent: turn.action for agent, turn in turns.items()})
        number += 1
        yield Step(number, turns, observations, rewards, terminations, truncations, infos)
