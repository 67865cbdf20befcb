"""Export a train-policy run's untrained network (its step-0 weights) behind the same guard.

    nice -n 10 python baselines/learned_select/untrained.py \
        baselines/learned_select/fallback/report.md runs/untrained.pt
    roco-env compare ... --policies learned_select:weights=runs/untrained.pt

Reads the exact command from a run's ``report.md``, builds the run's environment and its
seeded PPO model as ``roco-env train-policy`` does before its first step (the same seed
gives the same initial network) and writes that network as a weights file. Benchmarking it
beside the trained file says what the training itself contributed: the gain of the trained
network over this one, not over the guard's rule.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

from roco_env.training.rl.config import FLAGS
from roco_env.training.rl.curriculum import CurriculumEnv
from roco_env.training.rl.policy_export import save_policy
from roco_env.training.rl.ppo import build_model


def run_command(report: Path) -> list[str]:
    """The train-policy options of the command recorded in ``report`` (its first code block),
    without ``--out``."""
    blocks = report.read_text().split("```")
    if len(blocks) < 3 or not blocks[1].strip().startswith("roco-env train-policy"):
        raise ValueError(f"{report} holds no `roco-env train-policy` command in a code block")
    return [arg for arg in shlex.split(blocks[1].strip())[2:] if not arg.startswith("--out=")]


def main(argv: list[str]) -> int:
    cli = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    cli.add_argument("report", type=Path, help="a train-policy run's report.md")
    cli.add_argument("out", type=Path, help="the weights file to write")
    args = cli.parse_args(argv)
    parser = argparse.ArgumentParser(prog="train-policy")
    FLAGS.add_to(parser)
    config = FLAGS.parse(parser.parse_args(run_command(args.report)))
    env = CurriculumEnv(config)
    model = build_model(config, env)
    save_policy(args.out, model.policy, env, config,
                {"command": f"untrained network of {args.report}"})
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
