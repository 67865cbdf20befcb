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
That row is named :data:`RULE`; :func:`rule_spec` is the fixed policy it plays (e.g. hand
rule C, ``reject_untested:tested=roco_fallback,tested_within_m=0.5``). Reports and
checkpoints written before the row had its name call it ``reject_untested``
(:func:`with_rule_key` reads them).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from roco_env.policies import make_policy
from roco_env.policies.reject_untested import RejectUntestedParams
from roco_env.training.rl.config import PolicyTrainConfig
from roco_env.training.rl.curriculum import (
    Condition,
    condition_env,
    eval_conditions,
    rule_action,
    training_guard,
)

BASELINES = ("identity", "no_fusion", "coalign", "roco", "roco_antialias", "oracle")
RULE = "rule"  # the guard's rule alone, the baseline of a guarded network (rule_spec)
OLD_RULE = "reject_untested"  # RULE's name in reports and checkpoints written before

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


def rule_spec(config: PolicyTrainConfig) -> str:
    """The fixed policy spec whose actions the :data:`RULE` row plays: ``reject_untested``
    with ``action_base`` as its base (named where not the default), ``guard_prefer`` as
    ``tested`` and ``guard_prefer_within_m`` (m) as ``tested_within_m``."""
    params = []
    if config.action_base != RejectUntestedParams().base:
        params.append(f"base={config.action_base}")
    if config.guard_prefer:
        params.append(f"tested={config.guard_prefer}")
    if config.guard_prefer_within_m is not None:
        params.append(f"tested_within_m={config.guard_prefer_within_m:g}")
    return "reject_untested" + (":" + ",".join(params) if params else "")


def with_rule_key(baselines: dict[str, dict[str, float]]) -> dict[str, dict[str, float]]:
    """``baselines`` (name -> score) with :data:`OLD_RULE` renamed :data:`RULE`, in
    place in the order (a report or checkpoint written before the rename)."""
    return {RULE if name == OLD_RULE else name: score for name, score in baselines.items()}


def baselines_of(config: PolicyTrainConfig) -> tuple[str, ...]:
    """The baselines a run of ``config`` is compared with: :data:`BASELINES`, and
    :data:`RULE` when the network acts behind a guard."""
    return BASELINES + ((RULE,) if config.guard != "none" else ())


def evaluate_baseline(config: PolicyTrainConfig, name: str) -> dict[str, float]:
    """One of :func:`baselines_of` on the held-out conditions."""
    if name == RULE and config.guard != "none":
        guard = training_guard(config)

        def rule() -> Act:
            return lambda observation, info: rule_action(guard, observation)
        return evaluate(config, rule)
    if name == "no_fusion":
        return evaluate(config, lambda: make_policy("identity"), baseline=True, fusion="none")
    if name not in BASELINES:
        raise ValueError(f"baseline must be one of {list(baselines_of(config))}; got {name!r}")
    kwargs = {"privileged": True} if name == "oracle" else {}
    return evaluate(config, lambda: make_policy(name), baseline=True, **kwargs)
