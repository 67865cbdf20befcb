"""The training curriculum: one condition per episode, drawn from the seed and its index.

A :class:`Condition` (scenario, noise level, density, noise model, env seed, controlled
agent) is a pure function of ``(config.seed, episode index)``, so a resumed run replays
the episodes an uninterrupted run would have played. :class:`CurriculumEnv` is the
single-agent Gymnasium env PPO trains on: each episode an :class:`~roco_env.wrappers.EgoEnv`
of the drawn condition, its Dict observation flattened (keys in the space's order) and
divided by a fixed per-entry scale (:func:`observation_layout`). Every condition shares
the spaces: ``max_collaborators`` and ``max_boxes`` are fixed by the config.
With ``reward_over="base"`` (``"rule"``) a step's reward is paid relative to the base's
action (the guard's rule alone) on the same frame: a copy of the EgoEnv
(``copy.deepcopy``: its generators and aligners' state too) takes that action, when it
differs from the policy's on a filled slot.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces

from roco_env.policies.learned import Guard, scaled_observation
from roco_env.scenario import load_scenario
from roco_env.training.rl.config import PolicyTrainConfig, select_choices
from roco_env.wrappers import EgoEnv

# Training env seeds are drawn at or above this; held-out evaluation seeds lie below it
# (EVAL_SEED_BASE...) and `roco-env compare` uses 0, 1, 2...
TRAIN_SEED_BASE = 1_000_000
EVAL_SEED_BASE = 500
# The largest divisor of an observation entry (m for positions and boxes): an entry with
# wider or open bounds maps 50 to 1; scaled values are clipped to +-INPUT_CLIP.
SCALE_CAP = 50.0
INPUT_CLIP = 10.0


@dataclass(frozen=True)
class Condition:
    """One episode's setting: noise ``sigma_t`` m = ``sigma_r`` deg; density None = the
    scenario's own; ``agent_draw`` in [0, 1) picks the controlled agent by position."""

    scenario: str
    noise: float
    density: float | None
    noise_model: str
    seed: int
    agent_draw: float = 0.0


def env_overrides(config: PolicyTrainConfig) -> dict[str, Any]:
    """The scenario fields every training and evaluation env shares (spaces, mode, reward)."""
    overrides: dict[str, Any] = {"action.mode": config.action_mode,
                                 "max_collaborators": config.max_collaborators,
                                 "max_boxes": config.max_boxes, "reward": config.reward}
    if config.observation_mode != "raw":
        overrides["observation.mode"] = config.observation_mode
    if config.action_mode in ("residual", "gate") or config.observation_mode == "aligned":
        overrides["action.base"] = config.action_base
    if config.action_mode == "select":  # a scenario's own choices never replace them
        overrides["action.choices"] = select_choices(config)
    return overrides


def base_choice(config: PolicyTrainConfig) -> int:
    """The index of ``action_base`` among the select choices: the action the guard keys
    on and the reference action of ``reward_over`` (the config checks it is a choice)."""
    return select_choices(config).index(config.action_base)


def training_guard(config: PolicyTrainConfig) -> Guard | None:
    """The rule ``config.guard`` applies to every action (None for ``"none"``):
    ``reject_untested`` rejects the slots ``action_base`` left untested and takes the
    network's action elsewhere; ``keep_tested`` takes ``action_base`` where it tested
    (or ``guard_prefer`` within ``guard_prefer_within_m`` of it) and the network's
    action elsewhere."""
    if config.guard == "none":
        return None
    if config.guard == "keep_tested":
        choices = select_choices(config)
        prefer = choices.index(config.guard_prefer) if config.guard_prefer else None
        return Guard(base_choice(config), None, "keep", "network", prefer,
                     config.guard_prefer_within_m)
    return Guard(base_choice(config), None, "network")


def guarded_action(guard: Guard | None, action: np.ndarray, observation: dict) -> np.ndarray:
    """``action`` (N,) with the guard's rules applied on the Dict ``observation``
    (unchanged without a guard); reject is the index after the observation's choices."""
    if guard is None:
        return action
    diagnostics = observation["choice_diagnostics"]
    return guard.constrain(action, np.shape(diagnostics)[1], diagnostics,
                           observation["collab_mask"])


def reference_action(config: PolicyTrainConfig, guard: Guard | None,
                     observation: dict) -> np.ndarray:
    """(N,) the action ``reward_over`` pays against: ``base``, action_base's choice on every
    slot behind the guard; ``rule``, the guard's rule alone (:meth:`Guard.rule`)."""
    if config.reward_over == "rule":
        return rule_action(guard, observation)
    return guarded_action(guard, np.full(len(observation["collab_mask"]), base_choice(config)),
                          observation)


def rule_action(guard: Guard, observation: dict) -> np.ndarray:
    """(N,) the guard's rule alone (:meth:`Guard.rule`) on the Dict ``observation``: its
    tested slots' choice, its untested slots rejected (the index after the choices)."""
    diagnostics = observation["choice_diagnostics"]
    return guard.rule(np.shape(diagnostics)[1], diagnostics, observation["collab_mask"])


def draw_condition(config: PolicyTrainConfig, index: int) -> Condition:
    """The ``index``-th training episode's condition (a function of the seed and index)."""
    rng = np.random.default_rng([config.seed, index])
    scenario = config.scenarios[int(rng.integers(len(config.scenarios)))]
    noise = float(rng.uniform(config.noise_low, config.noise_high))
    factor = float(rng.uniform(config.density_low, config.density_high))
    base = load_scenario(scenario).traffic
    density = factor * base.density
    if base.layout == "parking_lot":  # a stall fill ratio
        density = min(density, 1.0)
    model = config.noise_models[int(rng.integers(len(config.noise_models)))]
    seed = int(rng.integers(TRAIN_SEED_BASE, 2**31 - 1))
    return Condition(scenario, noise, density, model, seed, float(rng.uniform()))


def eval_conditions(config: PolicyTrainConfig) -> list[Condition]:
    """The held-out evaluation: every scenario x ``eval_noises`` x ``eval_seeds`` seeds,
    Gaussian noise, the scenario's density, the first agent as ego."""
    return [Condition(scenario, float(noise), None, "gaussian", EVAL_SEED_BASE + seed)
            for scenario in config.scenarios for noise in config.eval_noises
            for seed in range(config.eval_seeds)]


def condition_env(config: PolicyTrainConfig, condition: Condition, *,
                  baseline: bool = False, **extra: Any) -> EgoEnv:
    """The EgoEnv of ``condition``; ``baseline``: in ``correction`` mode with the raw
    observation (a fixed policy's env); ``extra`` overrides fields (``fusion="none"``) or
    passes EgoEnv arguments; lean infos (``info_level="metrics"``) unless asked."""
    overrides = {**env_overrides(config), "sigma_t": condition.noise,
                 "sigma_r": condition.noise, "noise_model": condition.noise_model}
    if baseline:
        overrides["action.mode"] = "correction"
        overrides.pop("observation.mode", None)
        overrides.pop("action.base", None)
        overrides.pop("action.choices", None)
    if condition.density is not None:
        overrides["density"] = condition.density
    info_level = extra.pop("info_level", "metrics")
    probe = EgoEnv(condition.scenario, max_cycles=1, info_level="none", **overrides, **extra)
    agents = probe.env.possible_agents
    agent = agents[min(int(condition.agent_draw * len(agents)), len(agents) - 1)]
    probe.close()
    return EgoEnv(condition.scenario, max_cycles=config.episode_steps, agent=agent,
                  info_level=info_level, **overrides, **extra)


def observation_layout(space: spaces.Dict, only: list[str] | None = None) -> \
        tuple[list[tuple[str, tuple]], np.ndarray]:
    """(keys with shapes in the space's order, per-entry divisor) of a Dict of Boxes;
    ``only``: the keys to keep (empty or None: all; an unknown key is a ValueError naming
    ``observation_keys`` and the entries).

    The divisor is max(|low|, |high|) capped at :data:`SCALE_CAP` (also for open or zero
    bounds); a non-Box entry is a ValueError naming it."""
    unknown = sorted(set(only or ()) - set(space.spaces))
    if unknown:
        raise ValueError(f"train-policy: observation_keys names {unknown}, not entries of the "
                         f"observation; choose from {list(space.spaces)}")
    keys, scales = [], []
    for key, box in space.spaces.items():
        if only and key not in only:
            continue
        if not isinstance(box, spaces.Box):
            raise ValueError(f"observation[{key!r}] is a {type(box).__name__}; train-policy "
                             "flattens Box entries only")
        keys.append((key, tuple(box.shape)))
        bound = np.maximum(np.abs(box.low), np.abs(box.high)).astype(np.float64)
        bound[~np.isfinite(bound) | (bound == 0) | (bound > SCALE_CAP)] = SCALE_CAP
        scales.append(bound.reshape(-1))
    return keys, np.concatenate(scales)


class CurriculumEnv(gymnasium.Env):
    """Single-agent env over the curriculum; observations flat float32 (see module doc).

    ``episodes`` counts the episodes started; ``reset(seed=s)`` restarts the sequence of
    ``config`` with seed ``s`` (index 0), ``reset()`` plays the next index. Set
    ``episodes`` to resume a sequence.
    """

    def __init__(self, config: PolicyTrainConfig) -> None:
        self.config = config
        self.episodes = 0
        self._env: EgoEnv | None = None
        first = condition_env(config, draw_condition(config, 0))
        self.keys, self.scale = observation_layout(first.observation_space,
                                                   config.observation_keys)
        first.close()
        size = self.scale.shape[0]
        self.observation_space = spaces.Box(-np.inf, np.inf, (size,), np.float32)
        self.action_space = first.action_space
        self.condition: Condition | None = None
        self._fresh = False  # reset and not stepped since
        self.guard = training_guard(config)
        self._observation: dict | None = None  # the last Dict observation (the guard's)

    def resume_index(self) -> int:
        """The episode index a resumed run starts with: the one in progress if it has not
        been stepped (a vector env resets right after an episode ends), else the next."""
        return self.episodes - 1 if self._fresh else self.episodes

    def flat(self, observation: dict) -> np.ndarray:
        """The observation as the policy network reads it."""
        return scaled_observation(observation, self.keys, self.scale, INPUT_CLIP)

    def reset(self, *, seed: int | None = None,
              options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        if seed is not None:
            self.config = type(self.config)(**{**vars(self.config), "seed": int(seed)})
            self.episodes = 0
        if self._env is not None:
            self._env.close()
        self.condition = draw_condition(self.config, self.episodes)
        self.episodes += 1
        self._env = condition_env(self.config, self.condition)
        if self._env.action_space != self.action_space:
            raise ValueError(f"scenario {self.condition.scenario!r} gives the action space "
                             f"{self._env.action_space}, not {self.action_space}")
        observation, info = self._env.reset(seed=self.condition.seed)
        self._fresh = True
        self._observation = observation
        return self.flat(observation), info

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        if self._env is None:
            raise ValueError("step() called before reset()")
        action = guarded_action(self.guard, action, self._observation)
        reference = self._reference_reward(action)
        observation, reward, terminated, truncated, info = self._env.step(action)
        if self.config.reward_over != "none":
            reward = 0.0 if reference is None else float(reward) - reference
        self._fresh = False
        self._observation = observation
        return self.flat(observation), reward, terminated, truncated, info

    def _reference_reward(self, action: np.ndarray) -> float | None:
        """What :func:`reference_action` earns on this step's frame (``reward_over="base"``:
        action_base's choice on every slot behind the guard; ``"rule"``: the guard's rule
        alone), played on a copy of the env; None without ``reward_over`` or where it
        equals ``action`` on every filled slot (the step then pays 0 with
        ``reward_over``)."""
        if self.config.reward_over == "none":
            return None
        reference = reference_action(self.config, self.guard, self._observation)
        filled = np.asarray(self._observation["collab_mask"]) > 0
        if np.array_equal(reference[filled], np.asarray(action)[filled]):
            return None
        twin = copy.deepcopy(self._env)
        try:
            return float(twin.step(reference)[1])
        finally:
            twin.close()

    def close(self) -> None:
        if self._env is not None:
            self._env.close()
            self._env = None
