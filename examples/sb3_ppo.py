"""Train a select-mode policy with Stable-Baselines3 PPO on one agent (EgoEnv).

Per collaborator slot the agent picks identity / coalign / roco / roco_antialias or
rejects it (``action.mode: select``), seeing the collaborators' boxes in its own frame
plus roco_antialias's per-slot diagnostics and every choice's (``choice_diagnostics``:
its own diagnostics and its agreement with the others; ``observation.mode: aligned``); the reward is
the AP@0.7 gain over no fusion (0 = as good as ignoring the collaborators). At each
evaluation the script prints the learned policy's held-out mean per-step reward beside
the fixed baselines' on the same seeds, and the time per iteration. A longer run on a
curriculum of scenes is ``roco-env train-policy`` (docs/learning.md).

Needs stable-baselines3 (pip install 'roco-env[rl]'); without it this script says so.

    python examples/sb3_ppo.py [--iterations 4] [--quick]
"""

from __future__ import annotations

import argparse
import os
import sys
import time


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="urban_intersection")
    parser.add_argument("--noise", type=float, default=1.5, help="sigma_t (m) = sigma_r (deg)")
    parser.add_argument("--iterations", type=int, default=4)
    parser.add_argument("--quick", action="store_true", help="1 iteration, tiny batches")
    args = parser.parse_args()
    quick = args.quick or os.environ.get("ROCO_EXAMPLE_QUICK") == "1"
    try:
        from stable_baselines3 import PPO
    except ImportError as exc:
        print(f"Stable-Baselines3 is not available ({exc}); install it with: "
              "pip install 'roco-env[rl]'. Skipping this example.")
        return 0

    from roco_env.training.rl.config import build_config
    from roco_env.training.rl.curriculum import CurriculumEnv
    from roco_env.training.rl.evaluate import BASELINES, evaluate, evaluate_baseline
    from roco_env.training.rl.ppo import greedy

    steps = 2 if quick else 8  # env steps per episode
    rollout = 8 if quick else 256  # env steps per PPO iteration
    # One scenario at one noise level; the held-out evaluation uses other seeds.
    config = build_config({
        "scenarios": [args.scenario], "noise_low": args.noise, "noise_high": args.noise,
        "density_low": 1.0, "density_high": 1.0, "noise_models": ["gaussian"],
        "episode_steps": steps, "n_steps": rollout, "batch_size": min(64, rollout),
        "eval_every": rollout, "total_timesteps": rollout, "eval_noises": [args.noise],
        "eval_seeds": 1 if quick else 3})
    env = CurriculumEnv(config)  # an EgoEnv per episode, observations flattened and scaled
    model = PPO("MlpPolicy", env, n_steps=rollout, batch_size=config.batch_size, gamma=0.0,
                ent_coef=0.01, seed=0, device="cpu", verbose=0)
    baselines = {name: evaluate_baseline(config, name)["reward"] for name in BASELINES}
    shown = "  ".join(f"{name} {value:+.3f}" for name, value in baselines.items())
    for iteration in range(1 if quick else args.iterations):
        start = time.perf_counter()
        model.learn(rollout, reset_num_timesteps=False)
        seconds = time.perf_counter() - start
        learned = evaluate(config, lambda: greedy(model, env))["reward"]
        print(f"iteration {iteration + 1}: {seconds:.1f} s; held-out AP@0.7 gain per step: "
              f"learned {learned:+.3f} | {shown}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
