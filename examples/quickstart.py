"""Quickstart: build the env, let RoCo correct every agent's collaborator poses, print AP.

    python examples/quickstart.py [--policy roco] [--noise 0.4] [--steps 30] [--quick]

ROCO_EXAMPLE_QUICK=1 (or --quick) runs a few steps only (used by the tests).
"""

from __future__ import annotations

import argparse
import os

import roco_env
from roco_env.evaluation import info_frame_stats
from roco_env.metrics import APAccumulator
from roco_env.policies import make_policy


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="crowded_intersection")
    parser.add_argument("--policy", default="roco",
                        help="a policy name (`roco-env list policies`; default roco)")
    parser.add_argument("--noise", type=float, default=0.4, help="sigma_t (m) = sigma_r (deg)")
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--quick", action="store_true", help="3 steps, 2 CAVs")
    args = parser.parse_args()
    quick = args.quick or os.environ.get("ROCO_EXAMPLE_QUICK") == "1"
    extra = {"cavs": 2} if quick else {}
    steps = 3 if quick else args.steps

    env = roco_env.parallel_env(args.scenario, max_cycles=steps, sigma_t=args.noise,
                                sigma_r=args.noise, **extra)
    observations, infos = env.reset(seed=0)
    policies = {agent: make_policy(args.policy) for agent in env.agents}  # one per agent
    accumulator = APAccumulator()  # dataset AP over all agents and steps
    while env.agents:
        actions = {a: policies[a](observations[a], infos[a]) for a in env.agents}
        observations, rewards, terminations, truncations, infos = env.step(actions)
        for info in infos.values():
            if info.get("evaluated", True):
                accumulator.add_stats(info_frame_stats(info))
        mean_reward = sum(rewards.values()) / len(rewards)
        print(f"mean per-step AP@0.7 reward: {mean_reward:.3f}")
    ap = accumulator.ap()
    print(f"{args.policy} on {args.scenario}, noise {args.noise:g} m / {args.noise:g} deg: "
          f"AP@0.5 = {100 * ap[0.5]:.1f}%, AP@0.7 = {100 * ap[0.7]:.1f}%")


if __name__ == "__main__":
    main()
