"""What a network behind the keep_tested guard does with the slots roco_antialias left
untested, per scenario (training seeds; not shipped).

    nice -n 10 python baselines/learned_select/untested_decisions.py WEIGHTS \
        [--noise 3.0] [--seeds 4] [--steps 10]

Plays each scenario x noise level x seed (env seeds 1,000,000 and up, the training range;
never the held-out 0-2) with the policy of ``WEIGHTS`` acting for every agent in its own
env modes, and prints, per condition, how many untested filled slots it gave each choice
or rejected, in brackets the slots where that choice's pose is within 1 m / 1 deg of the
truth (for reject: where every choice's pose is off by more; the privileged truth is read
for these counts only).
"""

from __future__ import annotations

import argparse
from collections import defaultdict

import numpy as np
from env_hook import choice_errors
from privileged_bound import REJECT_ERROR

import roco_env
from roco_env.policies import make_policy
from roco_env.training.rl.curriculum import TRAIN_SEED_BASE


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("weights")
    parser.add_argument("--scenarios", nargs="+",
                        default=["urban_intersection", "parking_lot", "v2xset_like"])
    parser.add_argument("--noise", nargs="+", type=float, default=[3.0])
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--steps", type=int, default=10)
    args = parser.parse_args(argv)
    policy = make_policy("learned_select", weights=args.weights)
    if getattr(policy, "guard", None) is None:
        parser.error(f"weights {args.weights}: the file holds no guard, so no slot is "
                     "'untested' to it (train with --guard keep_tested or reject_untested)")
    choices = list(policy.env_overrides["action.choices"])
    names = [*choices, "reject"]
    print("| scenario | noise | untested slots | " + " | ".join(
        f"{name} (within {REJECT_ERROR:g})" for name in names) + " |")
    print("|---|---|---|" + "---|" * len(names))
    for scenario in args.scenarios:
        for noise in args.noise:
            counts: dict = defaultdict(lambda: np.zeros(2, dtype=int))
            for seed in range(TRAIN_SEED_BASE, TRAIN_SEED_BASE + args.seeds):
                _play(policy, scenario, noise, seed, args.steps, counts)
            total = sum(int(c[0]) for c in counts.values())
            print(f"| {scenario} | {noise} | {total} | " + " | ".join(
                f"{counts[k][0]} ({counts[k][1]})" for k in range(len(names))) + " |")


def _play(policy, scenario: str, noise: float, seed: int, steps: int, counts: dict) -> None:
    """Add one episode's untested slots to ``counts[action] = [slots, within 1]``."""
    env = roco_env.parallel_env(scenario, max_cycles=steps, sigma_t=noise, sigma_r=noise,
                                info_level="full", **policy.env_overrides)
    observations, infos = env.reset(seed=seed)
    while env.agents:
        actions = {}
        for agent in env.agents:
            observation, info = observations[agent], infos[agent]
            actions[agent] = action = policy(observation, info)
            mask = observation["collab_mask"]
            alignments = env.unwrapped._choices[agent] if hasattr(env, "unwrapped") \
                else env._choices[agent]
            n, errors = choice_errors(alignments, observation, info)
            untested = policy.guard.untested_slots(observation["choice_diagnostics"], mask)[:n]
            for slot in np.flatnonzero(untested):
                chosen = int(action[slot])
                right = chosen < len(errors) and errors[chosen, slot] <= REJECT_ERROR
                counts[chosen] += [1, int(right or
                                          (chosen == len(errors)
                                           and errors[:, slot].min() > REJECT_ERROR))]
        observations, _, _, _, infos = env.step(actions)
    env.close()


if __name__ == "__main__":
    main()
