"""Optional: train a shared select-mode PPO policy with RLlib on the PettingZoo env.

Needs ``ray[rllib]`` (pip install "ray[rllib]"); without it this script says so and
exits 0. Every agent shares one policy that, per collaborator slot, picks identity /
coalign / roco / roco_antialias or rejects it (``action.mode: select``, a MultiDiscrete
action RLlib's PPO takes as it is), seeing the collaborators' boxes in its own frame and
roco_antialias's diagnostics and every choice's (``choice_diagnostics``;
``observation.mode: aligned``, flattened by RLlib's
FlattenObservations connector). The reward is the AP@0.7 gain over no fusion, so doing
nothing useful scores 0. Each iteration prints RLlib's mean episode return (sampled
actions, every agent's rewards summed over the episode) beside the same return of the
fixed baselines (each agent running the policy; no fusion scores 0 by definition), and
the time per iteration. (The former correction-mode version printed ~95 with no
baseline: random actions scored 97.)

    python examples/rllib_ppo.py [--iterations 5] [--quick]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

# The env every agent acts in (docs/learning.md).
MODES = {"action.mode": "select", "observation.mode": "aligned",
         "action.base": "roco_antialias", "reward": "ap70_gain"}
BASELINES = ("identity", "coalign", "roco", "roco_antialias")


def baseline_returns(env_config: dict, seeds: int) -> dict[str, float]:
    """Mean episode return (every agent's rewards summed) of each fixed policy, acting in
    correction mode with one instance per agent, over seeds 0..seeds-1."""
    import numpy as np

    from roco_env.policies import make_policy

    returns = {}
    for name in BASELINES:
        totals = []
        for seed in range(seeds):
            env = make_env({**env_config, "baseline": True})
            observations, infos = env.reset(seed=seed)
            policies = {agent: make_policy(name) for agent in env.agents}
            total = 0.0
            while env.agents:
                actions = {a: policies[a](observations[a], infos[a]) for a in env.agents}
                observations, rewards, _, _, infos = env.step(actions)
                total += sum(rewards.values())
            totals.append(total)
        returns[name] = float(np.mean(totals))
    returns["no_fusion"] = 0.0  # the gain reward's zero
    return returns


def make_env(config: dict):
    """The parallel env of the example (``baseline``: correction mode, raw observations)."""
    import roco_env

    modes = {"reward": "ap70_gain"} if config.get("baseline") else MODES
    return roco_env.parallel_env(config["scenario"], max_cycles=config["steps"],
                                 sigma_t=config["noise"], sigma_r=config["noise"],
                                 **({"cavs": 2} if config["quick"] else {}), **modes)


def rllib_missing() -> str | None:
    """Why RLlib cannot be used here, or None when it can."""
    try:
        import ray.rllib  # noqa: F401
        from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv  # noqa: F401
    except ImportError as exc:
        return f"{exc}"
    return None


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="urban_intersection")
    parser.add_argument("--noise", type=float, default=1.5, help="sigma_t (m) = sigma_r (deg)")
    parser.add_argument("--iterations", type=int, default=5)
    parser.add_argument("--quick", action="store_true", help="1 iteration, tiny batches")
    args = parser.parse_args()
    quick = args.quick or os.environ.get("ROCO_EXAMPLE_QUICK") == "1"
    reason = rllib_missing()
    if reason is not None:
        print(f"RLlib is not available ({reason}); install it with: pip install 'ray[rllib]'. "
              "Skipping this optional example.")
        return 0

    import ray
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.connectors.env_to_module import FlattenObservations
    from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv
    from ray.tune.registry import register_env

    steps = 5 if quick else 20
    env_config = {"scenario": args.scenario, "steps": steps, "noise": args.noise,
                  "quick": quick}
    register_env("roco_parallel", lambda config: ParallelPettingZooEnv(make_env(config)))
    batch = 2 * steps if quick else 1000
    baselines = baseline_returns(env_config, 1 if quick else 3)
    shown = "  ".join(f"{name} {value:+.2f}" for name, value in baselines.items())
    config = (
        PPOConfig()
        .environment("roco_parallel", env_config=env_config)
        .env_runners(num_env_runners=0,
                     env_to_module_connector=lambda *_, **__: FlattenObservations(
                         multi_agent=True))
        .multi_agent(policies={"shared"}, policy_mapping_fn=lambda agent_id, *_, **__: "shared")
        .training(train_batch_size_per_learner=batch, minibatch_size=min(batch, 128),
                  num_epochs=1 if quick else 5)
    )
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        algorithm = config.build_algo()
        for iteration in range(1 if quick else args.iterations):
            start = time.perf_counter()
            result = algorithm.train()
            seconds = time.perf_counter() - start
            returns = result.get("env_runners", {}).get("episode_return_mean")
            learned = "n/a" if returns is None else f"{returns:+.2f}"
            print(f"iteration {iteration + 1}: {seconds:.1f} s; mean episode return "
                  f"learned {learned} | {shown}")
        algorithm.stop()
    finally:
        ray.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
