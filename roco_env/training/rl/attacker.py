"""Train a learned attacker with Stable-Baselines3 PPO against a fixed defence.

    python -m roco_env.training.rl.attacker --victims roco --out runs/attacker_roco
    python -m roco_env.training.rl.attacker --victims defend:base=roco --out runs/attacker_defend

One attacker (``attack.kind: learned``, one agent of the scene drawn per episode) is
``attacker_0`` of an :class:`~roco_env.attacks.adversarial_env.AdversarialEnv`; every
vehicle and RSU acts with the victims' policy spec (in the env modes it declares: ``defend``
in gate mode). :class:`AttackerEnv` is that agent as a Gymnasium env: its observation (its
vehicle's Dict observation) flattened and scaled as the learned policies' are
(:func:`roco_env.training.rl.curriculum.observation_layout`, clipped to
+-:data:`~roco_env.training.rl.curriculum.INPUT_CLIP`); its action the attack's Box.
Episode k is env seed ``seed + k``.

The reward (``--reward``): ``absolute`` is the learned attack's own (minus the victims'
mean AP@0.7 this step, minus the detection penalty), dominated by how much AP the scene
allows; ``twin`` adds the clean twin's AP@0.7 of the same victims on the same step (the
same seed played without the attack, once per training episode), so the attacker is paid
the AP it removes (a share, 0-1 per step) minus the penalty, and the zero action earns 0.

The held-out evaluation (:mod:`roco_env.training.rl.attacker_eval`) plays seeds from
:data:`EVAL_SEED` on with the greedy (mean) action and scores each episode against its
clean twin (played once) over the honest egos: the AP@0.7 it removes, attack success,
how often the victims rejected it and how often they rejected honest collaborators. It
runs before training, every ``eval_every`` env steps and after training; the report's
``best_stealthy`` is the evaluation removing the most AP while detected in under
:data:`~roco_env.training.rl.attacker_eval.STEALTH` of the attacker's slots, its model
saved as ``best.zip`` and played again on fresh seeds (from :data:`FRESH_SEED` on, as
many): the checkpoint was chosen on the held-out seeds, so its score there is the best of
several and flatters it; the fresh seeds' score does not. The options: :class:`AttackerTrainConfig` (:data:`FLAGS`). Writes
``curve.csv`` (mean and sd of the episode returns per PPO rollout), ``evaluations.csv``,
``curve.png``, ``report.json`` (the evaluations, the zero action's, the command) and
``attacker.zip`` (the final SB3 model). Deterministic on one machine (seeded torch and
numpy).
"""

from __future__ import annotations

import argparse
import functools
import json
import random
import shlex
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces

from roco_env.attacks.adversarial_env import AdversarialEnv
from roco_env.attacks.learned_attack import LearnedAttackParams
from roco_env.attacks.scoring import EpisodeLog
from roco_env.env import CollabPerceptionEnv
from roco_env.flags import SpecFlags
from roco_env.policies.learned import scaled_observation
from roco_env.policies.spec import merge_env_overrides, validate_policy_spec
from roco_env.rollout import play_episode
from roco_env.schema import ConfigError, build, check_fields, spec
from roco_env.training.rl.attacker_eval import best_stealthy, evaluate, write_report
from roco_env.training.rl.curriculum import INPUT_CLIP, observation_layout
from roco_env.training.rl.ppo import sb3_missing

__all__ = ["FLAGS", "AttackerEnv", "AttackerTrainConfig", "evaluate", "main", "train"]

EVAL_SEED = 500_000  # held-out evaluation seeds start here (training: seed + episode index)
FRESH_SEED = 600_000  # the best stealthy checkpoint's second evaluation starts here
ATTACKER = "attacker_0"
WHERE = "python -m roco_env.training.rl.attacker"


@dataclass
class AttackerTrainConfig:
    """The options of one learned attacker's training (module docstring). The attack's
    budget and penalty are checked as ``attack.params`` of ``attack.kind: learned``."""

    victims: str = spec("roco", doc="the victims' policy spec")
    scenario: str = spec("urban_intersection", doc="the scenario (a name or a YAML path)")
    cavs: int = spec(4, low=1, high=32, doc="CAVs (plus one RSU)")
    noise: float = spec(0.4, low=0.0, high=20.0, doc="sigma_t m = sigma_r deg")
    steps: int = spec(10, low=1, high=1000, doc="env steps per episode")
    timesteps: int = spec(1280, low=1, doc="PPO env steps")
    rollout: int = spec(128, low=1, doc="env steps per PPO update")
    budget_m: float = spec(3.0, doc="attack.params.budget_m: the largest pose translation, m")
    budget_deg: float = spec(3.0, doc="attack.params.budget_deg: the largest pose rotation, "
                             "degrees")
    ghosts: int = spec(5, doc="attack.params.ghosts: ghost boxes per message")
    detection_penalty: float = spec(1.0, doc="attack.params.detection_penalty: reward lost "
                                    "when every victim rejects the attacker")
    reward: str = spec("twin", choices=("twin", "absolute"),
                       doc="twin: paid the AP removed against the clean twin; absolute: "
                       "minus the attacked AP (module docstring)")
    eval_episodes: int = spec(3, low=1, high=1000, doc="held-out evaluation episodes")
    eval_every: int = spec(0, low=0, doc="env steps between held-out evaluations of the "
                           "greedy policy, a multiple of rollout (0: before and after "
                           "training only)")
    log_std_init: float = spec(0.0, low=-5.0, high=2.0,
                               doc="PPO's initial log standard deviation of its Gaussian "
                               "actions, in the action's [-1, 1] units (SB3's log_std_init; "
                               "0: std 1, the whole budget explored from the start)")
    seed: int = spec(0, low=0, high=2**31 - 1, doc="training seed (weights, episodes)")

    def __post_init__(self) -> None:
        check_fields(self, WHERE)
        if self.eval_every % self.rollout:
            raise ConfigError(f"{WHERE}: eval_every={self.eval_every} must be a multiple of "
                              f"rollout={self.rollout} (evaluations run between rollouts)")
        build(LearnedAttackParams, self.attack(), WHERE, "attack.params.")
        try:
            validate_policy_spec(self.victims)
        except ValueError as exc:
            raise ConfigError(f"{WHERE}: victims: {exc}") from exc

    def attack(self) -> dict[str, Any]:
        """The learned attack's ``attack.params``."""
        return {"budget_m": self.budget_m, "budget_deg": self.budget_deg,
                "ghosts": self.ghosts, "detection_penalty": self.detection_penalty}


# The command line's options, one per field of AttackerTrainConfig.
FLAGS = SpecFlags(AttackerTrainConfig, WHERE)


class AttackerEnv(gymnasium.Env):
    """``attacker_0`` as a Gymnasium env (module docstring).

    scenario: a scenario name; victims: the policy spec every vehicle and RSU acts with;
    attack: ``attack.params`` of the learned attack; noise: sigma_t m = sigma_r deg;
    steps: env steps per episode; seed: the first episode's env seed; twin_reward: pay the
    AP removed against the clean twin (module docstring); overrides: further scenario
    overrides. ``log``: the :class:`EpisodeLog` of the episode under way.
    """

    metadata = {"render_modes": []}

    def __init__(self, scenario: str, victims: str, attack: dict[str, Any], noise: float,
                 steps: int, seed: int = 0, twin_reward: bool = False,
                 **overrides: Any) -> None:
        self.spec_of_victims = validate_policy_spec(victims)
        policy = self.spec_of_victims.build()
        self._clean_overrides = merge_env_overrides(
            {**overrides, "sigma_t": noise, "sigma_r": noise}, policy, victims)
        self._scenario, self._steps_per_episode = scenario, int(steps)
        self.adversarial = AdversarialEnv(CollabPerceptionEnv(
            scenario, max_cycles=steps, **{**self._clean_overrides, "attack.kind": "learned",
                                          "attack.params": dict(attack)}))
        self.env = self.adversarial.env
        self.victims = {agent: policy if k == 0 else self.spec_of_victims.build()
                        for k, agent in enumerate(self.env.possible_agents)}
        self.keys, self.scale = observation_layout(self.adversarial.observation_space(ATTACKER))
        self.observation_space = spaces.Box(-INPUT_CLIP, INPUT_CLIP, self.scale.shape,
                                            np.float32)
        self.action_space = self.adversarial.action_space(ATTACKER)
        self.seed_base, self.episodes = int(seed), 0
        self.log = EpisodeLog()
        self._clean: dict[int, EpisodeLog] = {}
        self._target = attack.get("target")
        self._twin_reward = bool(twin_reward)
        self._twin_log: EpisodeLog | None = None
        self._last: tuple[dict, dict] | None = None
        self._steps = 0

    def flat(self, observation: dict) -> np.ndarray:
        """The network's input (module docstring)."""
        return scaled_observation(observation, self.keys, self.scale, INPUT_CLIP)

    def reset(self, *, seed: int | None = None,
              options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        episode_seed = self.seed_base + self.episodes if seed is None else seed
        self.episodes += 1
        if self._twin_reward:
            self._twin_log = self._play_clean(episode_seed)
        for policy in self.victims.values():
            policy.reset()
        observations, infos = self.adversarial.reset(seed=episode_seed)
        self._last, self._steps = (observations, infos), 0
        self.log = EpisodeLog(attackers=frozenset(
            self.adversarial.vehicle(k) for k in range(len(self.adversarial.attackers))))
        return self.flat(observations[ATTACKER]), infos[ATTACKER]

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        observations, infos = self._last
        actions = {agent: self.victims[agent](observations[agent], infos[agent])
                   for agent in self.env.possible_agents}
        observations, rewards, terminations, truncations, infos = self.adversarial.step(
            {**actions, ATTACKER: action})
        self._steps += 1
        self.log.record(self._steps, {a: infos[a] for a in self.env.possible_agents})
        self._last = (observations, infos)
        reward = float(rewards[ATTACKER])
        if self._twin_log is not None:
            reward += self._twin_ap(infos)
        return self.flat(observations[ATTACKER]), reward, \
            any(terminations.values()), any(truncations.values()), infos[ATTACKER]

    def _twin_ap(self, infos: dict) -> float:
        """The clean twin's AP@0.7 (undefined = 0) this step, mean over the agents the
        attack's reward scores (``target``, else the honest agents with an AP this step)."""
        victims = [agent for agent in self.env.possible_agents
                   if agent not in self.log.attackers and "ap70" in infos[agent]]
        scored = [self._target] if self._target is not None else victims
        if not scored:
            return 0.0
        return float(np.mean([self._twin_log.ap70[agent, self._steps] for agent in scored]))

    @functools.cached_property
    def twin(self) -> CollabPerceptionEnv:
        """The env without the attack (the clean twins' episodes)."""
        return CollabPerceptionEnv(self._scenario, max_cycles=self._steps_per_episode,
                                   **self._clean_overrides)

    def clean_log(self, seed: int) -> EpisodeLog:
        """The log of episode ``seed`` played by the victims without the attack, played
        once per env (call it between episodes: it resets the victims' policies)."""
        if seed not in self._clean:
            self._clean[seed] = self._play_clean(seed)
        return self._clean[seed]

    def _play_clean(self, seed: int) -> EpisodeLog:
        """Episode ``seed`` played by the victims without the attack (resets their
        policies)."""
        log = EpisodeLog()
        for step in play_episode(self.twin, self.victims, seed=seed,
                                 max_steps=self._steps_per_episode):
            log.record(step.number, step.infos)
        return log


def train(options: AttackerTrainConfig, out: Path, command: str) -> dict[str, Any]:
    """Train and evaluate (module docstring) into the folder ``out``; ``command``: the
    command line recorded in the report. Returns the report."""
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback
    from tqdm import tqdm

    def make(seed: int, twin_reward: bool) -> AttackerEnv:
        return AttackerEnv(options.scenario, options.victims, options.attack(), options.noise,
                           options.steps, seed=seed, twin_reward=twin_reward,
                           cavs=options.cavs, rsus=1)

    random.seed(options.seed)
    np.random.seed(options.seed)
    torch.manual_seed(options.seed)
    env = make(options.seed, options.reward == "twin")
    model = PPO("MlpPolicy", env, n_steps=options.rollout,
                batch_size=min(64, options.rollout), gamma=0.9, ent_coef=0.0,
                learning_rate=3e-4, seed=options.seed, device="cpu",
                policy_kwargs={"net_arch": [64, 64], "log_std_init": options.log_std_init},
                verbose=0)
    out.mkdir(parents=True, exist_ok=True)
    seeds = range(EVAL_SEED, EVAL_SEED + options.eval_episodes)
    held_out = make(EVAL_SEED, False)  # plays each clean twin once for every evaluation
    curve: list[dict[str, float]] = []
    evaluations: list[dict[str, float]] = []
    returns: list[float] = []
    started = time.perf_counter()

    def checkpoint(timesteps: int) -> None:
        """Evaluate the greedy policy after ``timesteps`` env steps of training; save it
        as best.zip when it is the best stealthy one so far."""
        scores = evaluate(held_out, lambda o: model.predict(o, deterministic=True)[0], seeds)
        evaluations.append({"timesteps": timesteps, **scores,
                            "wall_s": round(time.perf_counter() - started, 1)})
        bar.set_postfix(removed=f"{scores['removed']:.1f}",
                        detected=f"{scores['detection_rate']:.0%}")
        if best_stealthy(evaluations) is evaluations[-1]:
            model.save(out / "best.zip")

    class Curve(BaseCallback):
        """Mean and sd of the episode returns per rollout (the learning curve); the
        evaluations at the start of every ``eval_every``-th rollout."""

        def __init__(self) -> None:
            super().__init__()
            self.episode = 0.0

        def _on_rollout_start(self) -> None:
            if self.num_timesteps == 0 or (options.eval_every
                                           and self.num_timesteps % options.eval_every == 0):
                checkpoint(self.num_timesteps)

        def _on_step(self) -> bool:
            bar.update(1)
            self.episode += float(self.locals["rewards"][0])
            if self.locals["dones"][0]:
                returns.append(self.episode)
                self.episode = 0.0
            return True

        def _on_rollout_end(self) -> None:
            recent = returns[-max(1, options.rollout // options.steps):]
            curve.append({"timesteps": self.num_timesteps, "return": float(np.mean(recent)),
                          "return_sd": float(np.std(recent)),
                          "wall_s": round(time.perf_counter() - started, 1)})

    # progress on stderr: env steps, and the last held-out evaluation's AP removed / detection
    with tqdm(total=options.timesteps, desc="attacker", unit="step") as bar:
        model.learn(options.timesteps, callback=Curve())
        if evaluations[-1]["timesteps"] != model.num_timesteps:
            checkpoint(model.num_timesteps)
    model.save(out / "attacker.zip")
    zero = evaluate(held_out, lambda o: np.zeros(env.action_space.shape, np.float32), seeds)
    best = best_stealthy(evaluations)
    if best is not None:
        chosen = PPO.load(out / "best.zip", device="cpu")
        fresh = range(FRESH_SEED, FRESH_SEED + options.eval_episodes)
        best = {**best, "model": "best.zip", "fresh_seeds": evaluate(
            make(FRESH_SEED, False), lambda o: chosen.predict(o, deterministic=True)[0], fresh)}
    report = {"command": command, "victims": options.victims, "attack": options.attack(),
              "reward": options.reward, "scenario": options.scenario, "noise": options.noise,
              "steps": options.steps, "timesteps": options.timesteps,
              "eval_episodes": options.eval_episodes, "eval_seeds": [seeds[0], seeds[-1]],
              "wall_s": round(time.perf_counter() - started, 1),
              "curve": curve, "evaluations": evaluations, "learned": evaluations[-1],
              "best_stealthy": best,
              "zero_action": zero}
    write_report(out, report)
    return report

def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog=WHERE, description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    FLAGS.add_to(parser)
    args = parser.parse_args(argv)
    try:
        options = FLAGS.parse(args)
        missing = sb3_missing()
        if missing:
            raise ValueError(f"Stable-Baselines3 is not available ({missing})")
        command = f"{WHERE} " + shlex.join([f"--out={args.out}", *FLAGS.argv(options)])
        report = train(options, args.out, command)
    except ValueError as exc:
        print(f"{WHERE}: error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps({k: report[k] for k in ("victims", "learned", "best_stealthy", "zero_action",
                                             "wall_s")},
                     indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
