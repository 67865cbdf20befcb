"""Train a learned attacker with Stable-Baselines3 PPO against a fixed defence.

    python -m roco_env.training.rl.attacker --victims roco --out runs/attacker_roco
    python -m roco_env.training.rl.attacker --victims defend:base=roco --out runs/attacker_defend

One attacker (``attack.kind: learned``, one agent of the scene drawn per episode) is
``attacker_0`` of an :class:`~roco_env.attacks.adversarial_env.AdversarialEnv`; every
vehicle and RSU acts with the victims' policy spec (in the env modes it declares: ``defend``
in gate mode). :class:`AttackerEnv` is that agent as a Gymnasium env: its observation (its
vehicle's Dict observation) flattened, divided by :data:`SCALE` and clipped to
+-:data:`CLIP`; its action the attack's Box. Episode k is env seed ``seed + k``; the held-out
evaluation plays seeds from :data:`EVAL_SEED` on with the greedy (mean) action and scores
each episode against its clean twin (the same seed without the attack) over the honest
egos (:func:`roco_env.attacks.scoring.attack_scores`): the AP@0.7 it removes and how often
the victims rejected it. Writes ``curve.csv`` (mean episode return per PPO rollout),
``curve.png``, ``report.json`` (the evaluation, the zero action's, the command) and
``attacker.zip`` (the SB3 model). Deterministic on one machine (seeded torch and numpy).
"""

from __future__ import annotations

import argparse
import csv
import json
import random
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces

from roco_env.attacks.adversarial_env import AdversarialEnv
from roco_env.attacks.scoring import EpisodeLog, attack_scores
from roco_env.env import CollabPerceptionEnv
from roco_env.policies.spec import merge_env_overrides, parse_policy_spec, validate_policy_spec
from roco_env.training.rl.ppo import sb3_missing

__all__ = ["AttackerEnv", "evaluate", "main", "train"]

SCALE, CLIP = 50.0, 10.0  # metres map 50 m to 1; the flat observation is clipped to +-10
EVAL_SEED = 500_000  # held-out evaluation seeds start here (training: seed + episode index)
ATTACKER = "attacker_0"


class AttackerEnv(gymnasium.Env):
    """``attacker_0`` as a Gymnasium env (module docstring).

    scenario: a scenario name; victims: the policy spec every vehicle and RSU acts with;
    attack: ``attack.params`` of the learned attack; noise: sigma_t m = sigma_r deg;
    steps: env steps per episode; seed: the first episode's env seed; clean: play the
    episode without the attack (the clean twin; the attacker's actions are ignored);
    overrides: further scenario overrides.
    """

    metadata = {"render_modes": []}

    def __init__(self, scenario: str, victims: str, attack: dict[str, Any], noise: float,
                 steps: int, seed: int = 0, clean: bool = False, **overrides: Any) -> None:
        self.spec_of_victims = validate_policy_spec(victims)
        policy = self.spec_of_victims.build()
        given = {**overrides, "sigma_t": noise, "sigma_r": noise,
                 "attack.kind": "learned", "attack.params": dict(attack)}
        self.adversarial = AdversarialEnv(CollabPerceptionEnv(
            scenario, max_cycles=steps, **merge_env_overrides(given, policy, victims)))
        self.env = self.adversarial.env
        self.clean = clean
        if clean:
            self.twin = CollabPerceptionEnv(scenario, max_cycles=steps, **merge_env_overrides(
                {**overrides, "sigma_t": noise, "sigma_r": noise}, policy, victims))
        self.victims = {agent: policy if k == 0 else self.spec_of_victims.build()
                        for k, agent in enumerate(self.env.possible_agents)}
        self.observation_layout = self.adversarial.observation_space(ATTACKER)
        size = spaces.flatdim(self.observation_layout)
        self.observation_space = spaces.Box(-CLIP, CLIP, (size,), np.float32)
        self.action_space = self.adversarial.action_space(ATTACKER)
        self.seed_base, self.episodes = int(seed), 0
        self.log = EpisodeLog()
        self._last: tuple[dict, dict] | None = None
        self._steps = 0

    def flat(self, observation: dict) -> np.ndarray:
        """The network's input: the flattened observation / SCALE, clipped to +-CLIP."""
        flat = spaces.flatten(self.observation_layout, observation) / SCALE
        return np.clip(flat, -CLIP, CLIP).astype(np.float32)

    def reset(self, *, seed: int | None = None,
              options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        episode_seed = self.seed_base + self.episodes if seed is None else seed
        self.episodes += 1
        for policy in self.victims.values():
            policy.reset()
        observations, infos = self.adversarial.reset(seed=episode_seed)
        if self.clean:  # the twin's views; the attacker's observation is unused
            observations, infos = self.twin.reset(seed=episode_seed)
            observations, infos = {**observations, ATTACKER: None}, {**infos, ATTACKER: {}}
        self._last, self._steps = (observations, infos), 0
        self.log = EpisodeLog(attackers=frozenset(
            self.adversarial.vehicle(k) for k in range(len(self.adversarial.attackers))))
        return self._observation(observations), infos[ATTACKER]

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        observations, infos = self._last
        actions = {agent: self.victims[agent](observations[agent], infos[agent])
                   for agent in self.env.possible_agents}
        if self.clean:
            observations, rewards, terminations, truncations, infos = self.twin.step(actions)
            reward, observations = 0.0, {**observations, ATTACKER: None}
            infos = {**infos, ATTACKER: {}}
        else:
            observations, rewards, terminations, truncations, infos = self.adversarial.step(
                {**actions, ATTACKER: action})
            reward = rewards[ATTACKER]
        self._steps += 1
        self.log.record(self._steps, {a: infos[a] for a in self.env.possible_agents})
        self._last = (observations, infos)
        done = any(truncations.values())
        return self._observation(observations), float(reward), \
            any(terminations.values()), done, infos[ATTACKER]

    def _observation(self, observations: dict) -> np.ndarray:
        seen = observations[ATTACKER]
        return self.flat(seen) if seen is not None else np.zeros(self.observation_space.shape,
                                                                np.float32)


def evaluate(make: Callable[[bool], AttackerEnv], act: Callable[[np.ndarray], np.ndarray],
             seeds: Sequence[int]) -> dict[str, float]:
    """The attack scores (:func:`roco_env.attacks.scoring.attack_scores`), mean over the
    ``seeds`` episodes, of ``act`` (flat observation -> action) against the clean twins;
    ``make(clean)`` builds the env."""
    attacked_env, clean_env = make(False), make(True)
    rows = []
    for seed in seeds:
        logs = []
        for env in (attacked_env, clean_env):
            observation, _ = env.reset(seed=seed)
            done = False
            while not done:
                observation, _, terminated, truncated, _ = env.step(act(observation))
                done = terminated or truncated
            logs.append(env.log)
        clean = logs[1]
        clean.attackers = logs[0].attackers
        rows.append(attack_scores(logs[0], clean))
    return {key: float(np.nanmean([row[key] for row in rows])) for key in rows[0]}


def train(args: argparse.Namespace) -> dict[str, Any]:
    """Train and evaluate (module docstring); returns the report."""
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback

    attack = {"budget_m": args.budget_m, "budget_deg": args.budget_deg,
              "ghosts": args.ghosts, "detection_penalty": args.detection_penalty}

    def make(clean: bool = False, seed: int = args.seed) -> AttackerEnv:
        return AttackerEnv(args.scenario, args.victims, attack, args.noise, args.steps,
                           seed=seed, clean=clean, cavs=args.cavs, rsus=1)

    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    env = make()
    model = PPO("MlpPolicy", env, n_steps=args.rollout, batch_size=min(64, args.rollout),
                gamma=0.9, ent_coef=0.0, learning_rate=3e-4, seed=args.seed, device="cpu",
                policy_kwargs={"net_arch": [64, 64]}, verbose=0)
    curve: list[dict[str, float]] = []
    returns: list[float] = []
    started = time.perf_counter()

    class Curve(BaseCallback):
        """Mean episode return per rollout (the learning curve)."""

        def __init__(self) -> None:
            super().__init__()
            self.episode = 0.0

        def _on_step(self) -> bool:
            self.episode += float(self.locals["rewards"][0])
            if self.locals["dones"][0]:
                returns.append(self.episode)
                self.episode = 0.0
            return True

        def _on_rollout_end(self) -> None:
            recent = returns[-max(1, args.rollout // args.steps):]
            curve.append({"timesteps": self.num_timesteps, "return": float(np.mean(recent)),
                          "wall_s": round(time.perf_counter() - started, 1)})

    model.learn(args.timesteps, callback=Curve())
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    model.save(out / "attacker.zip")
    seeds = range(EVAL_SEED, EVAL_SEED + args.eval_episodes)
    greedy = evaluate(make, lambda o: model.predict(o, deterministic=True)[0], seeds)
    zero = evaluate(make, lambda o: np.zeros(env.action_space.shape, np.float32), seeds)
    report = {"command": " ".join(sys.argv), "victims": args.victims, "attack": attack,
              "scenario": args.scenario, "noise": args.noise, "steps": args.steps,
              "timesteps": args.timesteps, "wall_s": round(time.perf_counter() - started, 1),
              "curve": curve, "learned": greedy, "zero_action": zero}
    _write(out, report)
    return report


def _write(out: Path, report: dict[str, Any]) -> None:
    """report.json, curve.csv and curve.png."""
    (out / "report.json").write_text(json.dumps(report, indent=2), encoding="utf-8")
    with (out / "curve.csv").open("w", newline="", encoding="utf-8") as handle:
        writer = csv.DictWriter(handle, fieldnames=["timesteps", "return", "wall_s"])
        writer.writeheader()
        writer.writerows(report["curve"])
    import matplotlib.pyplot as plt

    figure, axis = plt.subplots(figsize=(5, 3.2))
    axis.plot([p["timesteps"] for p in report["curve"]], [p["return"] for p in report["curve"]],
              marker="o")
    axis.set_xlabel("env steps")
    axis.set_ylabel("mean episode return")
    axis.set_title(f"learned attacker vs {report['victims']}")
    axis.grid(alpha=0.3)
    figure.tight_layout()
    figure.savefig(out / "curve.png", dpi=120)
    plt.close(figure)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m roco_env.training.rl.attacker",
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--victims", default="roco", help="the victims' policy spec")
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--scenario", default="urban_intersection")
    parser.add_argument("--cavs", type=int, default=4, help="CAVs (plus one RSU)")
    parser.add_argument("--noise", type=float, default=0.4, help="sigma_t m = sigma_r deg")
    parser.add_argument("--steps", type=int, default=10, help="env steps per episode")
    parser.add_argument("--timesteps", type=int, default=1280, help="PPO env steps")
    parser.add_argument("--rollout", type=int, default=128, help="env steps per PPO update")
    parser.add_argument("--budget-m", type=float, default=3.0)
    parser.add_argument("--budget-deg", type=float, default=3.0)
    parser.add_argument("--ghosts", type=int, default=5)
    parser.add_argument("--detection-penalty", type=float, default=1.0)
    parser.add_argument("--eval-episodes", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    missing = sb3_missing()
    if missing:
        print(f"{parser.prog}: Stable-Baselines3 is not available ({missing})", file=sys.stderr)
        return 2
    try:
        parse_policy_spec(args.victims)
        for name in ("steps", "timesteps", "rollout", "eval_episodes"):
            if getattr(args, name) < 1:
                raise ValueError(f"--{name.replace('_', '-')} must be >= 1")
        report = train(args)
    except ValueError as exc:
        print(f"{parser.prog}: error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps({k: report[k] for k in ("victims", "learned", "zero_action", "wall_s")},
                     indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
