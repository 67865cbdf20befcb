"""``roco-env train-policy``'s loop: Stable-Baselines3 PPO on the curriculum, resumable.

Deterministic on one machine: the weights' initialisation, action sampling and minibatch
order come from torch's and numpy's global generators, seeded from ``config.seed`` and
saved in each checkpoint; each episode's condition is a function of the seed and its index
(:mod:`roco_env.training.rl.curriculum`). Rollouts hold whole episodes, so a checkpoint
(every ``eval_every`` steps, after the held-out evaluation) falls between two episodes and
a rerun with the same output folder continues exactly where the last checkpoint left off.
"""

from __future__ import annotations

import random
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from roco_env.training.rl.checkpoint import load_state, restore_checkpoint, save_checkpoint
from roco_env.training.rl.config import PolicyTrainConfig
from roco_env.training.rl.curriculum import CurriculumEnv, guarded_action
from roco_env.training.rl.evaluate import (
    baselines_of,
    evaluate,
    evaluate_baseline,
    with_rule_key,
)


@dataclass
class TrainResult:
    """A finished run: the SB3 model, its curriculum env, the learning curve (one entry per
    evaluation: timesteps, wall_s, reward, ap70), the baselines' scores, the config."""

    model: Any
    env: CurriculumEnv
    curve: list[dict[str, float]]
    baselines: dict[str, dict[str, float]]
    config: PolicyTrainConfig


def sb3_missing() -> str | None:
    """Why Stable-Baselines3 cannot be imported, or None."""
    try:
        import stable_baselines3  # noqa: F401
    except ImportError as exc:
        return f"{exc}; install it with: pip install 'roco-env[rl]'"
    return None


def build_model(config: PolicyTrainConfig, env: CurriculumEnv) -> Any:
    """A seeded SB3 PPO with an MLP actor and critic (tanh) on ``env``."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import DummyVecEnv

    random.seed(config.seed)
    np.random.seed(config.seed)
    torch.manual_seed(config.seed)
    arch = list(config.net_arch)
    return PPO("MlpPolicy", DummyVecEnv([lambda: env]), n_steps=config.n_steps,
               batch_size=config.batch_size, n_epochs=config.n_epochs,
               learning_rate=config.learning_rate, gamma=config.gamma,
               gae_lambda=config.gae_lambda, ent_coef=config.ent_coef,
               clip_range=config.clip_range, device="cpu", seed=None, verbose=0,
               policy_kwargs={"net_arch": {"pi": arch, "vf": arch},
                              "activation_fn": torch.nn.Tanh})


def greedy(model: Any, env: CurriculumEnv) -> Callable[[dict, dict], np.ndarray]:
    """``act(obs, info)``: the model's deterministic action on a Dict observation (behind
    the training guard, as the exported policy acts)."""
    def act(observation: dict, info: dict | None = None) -> np.ndarray:
        action, _ = model.predict(env.flat(observation), deterministic=True)
        return guarded_action(env.guard, action, observation)
    return act


def train(config: PolicyTrainConfig, out: Path, progress: bool = True,
          log: Callable[[str], None] = print) -> TrainResult:
    """Train (or resume the run in ``out``) and return the result; writes checkpoints."""
    reason = sb3_missing()
    if reason is not None:
        raise ValueError(f"train-policy needs Stable-Baselines3: {reason}")
    from stable_baselines3.common.callbacks import BaseCallback
    from tqdm import tqdm

    torch.set_num_threads(config.threads)
    state = load_state(out, config)
    env = CurriculumEnv(config)
    model = build_model(config, env)
    if state is None:
        baselines = {}
        for name in baselines_of(config):
            baselines[name] = evaluate_baseline(config, name)
            log(f"baseline {name}: reward {baselines[name]['reward']:.4f} "
                f"AP@0.7 {baselines[name]['ap70']:.4f}")
        curve: list[dict[str, float]] = []
        wall = 0.0
    else:
        restore_checkpoint(out, model, state)
        env.episodes = int(state["episodes"])
        baselines, curve = with_rule_key(state["baselines"]), state["curve"]
        wall = float(state["wall_s"])
        log(f"resuming {out} at {model.num_timesteps} of {config.total_timesteps} steps")

    def checkpoint(started: float) -> None:
        nonlocal wall
        score = evaluate(config, lambda: greedy(model, env))
        wall += time.perf_counter() - started
        curve.append({"timesteps": int(model.num_timesteps), "wall_s": round(wall, 1),
                      **score})
        save_checkpoint(out, model, env.resume_index(),
                        {"config": asdict(config), "baselines": baselines, "curve": curve,
                         "wall_s": wall})
        log(f"{model.num_timesteps} steps, {wall:.0f} s: reward {score['reward']:.4f} "
            f"AP@0.7 {score['ap70']:.4f}")

    if state is None:
        checkpoint(time.perf_counter())

    class Bar(BaseCallback):
        def _on_step(self) -> bool:
            bar.update(1)
            return True

    with tqdm(total=config.total_timesteps, initial=model.num_timesteps, disable=not progress,
              desc="train-policy", unit="step") as bar:
        while model.num_timesteps < config.total_timesteps:
            started = time.perf_counter()
            chunk = min(config.eval_every, config.total_timesteps - model.num_timesteps)
            model.learn(chunk, reset_num_timesteps=False, callback=Bar())
            checkpoint(started)
    return TrainResult(model, env, curve, baselines, config)
