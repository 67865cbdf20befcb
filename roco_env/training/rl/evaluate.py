"""Held-out evaluation of a policy and of the fixed baselines on the same conditions.

Every score is the mean per-step reward (the config's, e.g. AP@0.7 gain: fused AP@0.7
minus the ego's own AP@0.7, in AP points 0..1) and the mean per-step AP@0.7 (steps with
an undefined AP left out) of the controlled agent over :func:`eval_conditions`. The
baselines run in ``correction`` mode with their policy (the same conditions, seeds and
reward; selecting aligner k equals aligner k, tests/test_action_modes.py): identity,
no fusion (``fusion="none"``), coalign, roco, roco_antialias and the oracle. A network
trained behind a guard is also compared with the guard's rule alone (:func:`baselines_of`,
:meth:`~roco_env.policies.learned.Guard.rule`): its tested slots' choice (the base
aligner's, or ``guard_prefer``'s within ``guard_prefer_within_m``), its untested slots
rejected, in the training env's mode; what the network adds is its score minus that row.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from roco_env.policies import make_policy
from roco_env.training.rl.config import PolicyTrainConfig
from roco_env.training.rl.curriculum import (
    Condition,
    condition_env,
    eval_conditions,
    training_guard,
)

BASELINES = ("identity", "no_fusion", "coalign", "roco", "roco_antialias", "oracle")
RULE = "reject_untested"  # the guard's rule alone, the baseline of a guarded network

Act = Callable[[dict, dict], np.ndarray]


def play(config: PolicyTrainConfig, condition: Condition, act: Act, **env_kwargs) -> \
        tuple[list[float], list[float]]:
    """(rewards, defined AP@0.7 values) of one episode where ``act(obs, info)`` acts."""
    env = condition_env(config, condition, **env_kwargs)
    try:
        observation, info = env.reset(seed=condition.seed)
        rewards, ap70 = [], []
        done = False
        while not done:
            observation, reward, terminated, truncated, info = env.step(act(observation, info))
            rewards.append(float(reward))
            if info["ap70"] >= 0:
                ap70.append(float(info["ap70"]))
            done = terminated or truncated
        return rewards, ap70
    finally:
        env.close()


def evaluate(config: PolicyTrainConfig, make_act: Callable[[], Act],
             **env_kwargs) -> dict[str, float]:
    """Mean per-step reward and AP@0.7 over the held-out conditions (a fresh ``make_act()``
    per episode: stateful policies start afresh)."""
    rewards: list[float] = []
    ap70: list[float] = []
    for condition in eval_conditions(config):
        episode_rewards, episode_ap = play(config, condition, make_act(), **env_kwargs)
        rewards += episode_rewards
        ap70 += episode_ap
    return {"reward": float(np.mean(rewards)), "ap70": float(np.mean(ap70)) if ap70 else -1.0,
            "steps": len(rewards)}


def baselines_of(config: PolicyTrainConfig) -> tuple[str, ...]:
    """The baselines a run of ``config`` is compared with: :data:`BASELINES`, and
    :data:`RULE` when the network acts behind a guard."""
    return BASELINES + ((RULE,) if config.guard != "none" else ())


def evaluate_baseline(config: PolicyTrainConfig, name: str) -> dict[str, float]:
    """One of :func:`baselines_of` on the held-out conditions."""
    if name == RULE and config.guard != "none":
        guard = training_guard(config)

        def rule() -> Act:
            return lambda observation, info: guard.rule(
                np.shape(observation["choice_diagnostics"])[1],
                observation["choice_diagnostics"], observation["collab_mask"])
        return evaluate(config, rule)
    if name == "no_fusion":
        return evaluate(config, lambda: make_policy("identity"), baseline=True, fusion="none")
    if name not in BASELINES:
        raise ValueError(f"baseline must be one of {list(baselines_of(config))}; got {name!r}")
    kwargs = {"privileged": True} if name == "oracle" else {}
    return evaluate(config, lambda: make_policy(name), baseline=True, **kwargs)
