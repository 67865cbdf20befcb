"""Optional: train a shared PPO correction policy with RLlib on the PettingZoo env.

Needs ``ray[rllib]`` (pip install "ray[rllib]"); without it this script says so and
exits 0. Every agent shares one policy; observations are flattened (RLlib's
FlattenObservations connector) and so are the (N, 3) corrections
(roco_env.wrappers.FlattenActions: PPO needs one-dimensional actions); the reward is
the per-step AP@0.7 of the agent's fused detections (env default).

    python examples/rllib_ppo.py [--iterations 5] [--quick]
"""

from __future__ import annotations

import argparse
import os
import sys


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
    parser.add_argument("--noise", type=float, default=0.4, help="sigma_t (m) = sigma_r (deg)")
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

    import roco_env
    from roco_env.wrappers import FlattenActions

    steps = 5 if quick else 50
    register_env("roco_parallel", lambda config: ParallelPettingZooEnv(FlattenActions(
        roco_env.parallel_env(config["scenario"], max_cycles=config["steps"],
                              sigma_t=config["noise"], sigma_r=config["noise"],
                              **({"cavs": 2} if config["quick"] else {})))))
    batch = 2 * steps if quick else 1000
    config = (
        PPOConfig()
        .environment("roco_parallel", env_config={"scenario": args.scenario, "steps": steps,
                                                  "noise": args.noise, "quick": quick})
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
            result = algorithm.train()
            returns = result.get("env_runners", {}).get("episode_return_mean")
            print(f"iteration {iteration + 1}: mean episode return {returns}")
        algorithm.stop()
    finally:
        ray.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
