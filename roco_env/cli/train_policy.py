"""``roco-env train-policy``: PPO (Stable-Baselines3) on a curriculum; weights + report."""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    from roco_env.training.rl.config import FLAGS

    p = subparsers.add_parser(
        "train-policy",
        help="train a learned alignment-decision policy with PPO (weights + report)",
        description="Train one policy with Stable-Baselines3 PPO in an action mode and "
        "observation mode on a curriculum (scenario, noise level, density and noise model "
        "drawn per episode), evaluate it and the fixed baselines on held-out seeds, and write "
        "OUT/learned_<mode>.pt, OUT/report.md, OUT/report.json and OUT/learning_curve.png. "
        "Re-running with the same --out and options resumes from the last checkpoint. "
        "Needs pip install 'roco-env[rl]'.",
    )
    p.add_argument("--out", required=True, type=Path, help="output folder (resumable)")
    p.add_argument("--quiet", action="store_true", help="no progress bar or log lines")
    FLAGS.add_to(p)
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from roco_env.sensing.learned.model import sha256_of
    from roco_env.training.rl.config import FLAGS
    from roco_env.training.rl.policy_export import save_policy
    from roco_env.training.rl.policy_report import write_report
    from roco_env.training.rl.ppo import train

    config = FLAGS.parse(args)
    command = "roco-env train-policy " + shlex.join([f"--out={args.out}", *FLAGS.argv(config)])
    args.out.mkdir(parents=True, exist_ok=True)
    log = (lambda message: None) if args.quiet else \
        (lambda message: print(message, file=sys.stderr, flush=True))
    result = train(config, args.out, progress=not args.quiet, log=log)
    weights = args.out / f"learned_{config.action_mode}.pt"
    save_policy(weights, result.model.policy, result.env, config,
                {"command": command, "final": result.curve[-1],
                 "baselines": result.baselines})
    write_report(result, args.out, command, weights, sha256_of(weights))
    final = result.curve[-1]
    print(f"wrote {weights} and the report in {args.out}")
    print(f"  learned: reward {final['reward']:.4f}, AP@0.7 {final['ap70']:.4f}")
    for name, score in result.baselines.items():
        print(f"  {name}: reward {score['reward']:.4f}, AP@0.7 {score['ap70']:.4f}")
    return 0
