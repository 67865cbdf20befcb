"""``roco-env train-detector``: train the learned BEV detector and write weights + report."""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    from roco_env.training.train import TrainConfig

    d = TrainConfig()

    p = subparsers.add_parser(
        "train-detector",
        help="train the learned BEV detector in the simulator (weights + report)",
        description="Generate training scenes from the scenario library (seeds disjoint from "
        "evaluation seeds), train the learned BEV detector deterministically, and write "
        "OUT/bev_detector.pt, OUT/report.md, OUT/report.json and OUT/loss_curves.png.",
    )
    p.add_argument("--out", required=True, type=Path, help="output folder")
    p.add_argument("--seed", type=int, default=d.seed, help="training seed (default %(default)s)")
    p.add_argument("--steps", type=int, default=d.steps,
                   help="optimiser steps (default %(default)s)")
    p.add_argument("--train-scenes", type=int, default=d.train_scenes,
                   help="training scenes (default %(default)s)")
    p.add_argument("--val-scenes", type=int, default=d.val_scenes,
                   help="validation scenes of urban_intersection (default %(default)s; 0 = none)")
    p.add_argument("--scenes-per-step", type=int, default=d.scenes_per_step,
                   help="scenes per batch (default %(default)s)")
    p.add_argument("--lr", type=float, default=d.lr, help="peak learning rate (default %(default)s)")
    p.add_argument("--widths", type=int, nargs=3, default=d.widths, metavar=("W1", "W2", "C"),
                   help="network widths (default %(default)s)")
    p.add_argument("--scenarios", nargs="+", default=list(d.scenarios),
                   help="training scenarios (default: the synthetic library)")
    p.add_argument("--pose-sigma-t", type=float, default=d.pose_sigma_t,
                   help="pose noise of the fused loss, translation std in m (default "
                   "%(default)s, the RoCo paper's training protocol)")
    p.add_argument("--pose-sigma-r", type=float, default=d.pose_sigma_r,
                   help="pose noise of the fused loss, rotation std in degrees (default "
                   "%(default)s)")
    p.add_argument("--threads", type=int, default=d.threads,
                   help="torch CPU threads (default %(default)s)")
    p.add_argument("--workers", type=int, default=d.workers,
                   help="processes generating scenes and batches (default %(default)s: none; "
                   "the weights do not depend on it)")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from roco_env.sensing.learned.model import SHIPPED_WEIGHTS, save_checkpoint, sha256_of
    from roco_env.training.report import write_report
    from roco_env.training.train import TrainConfig, train

    config = TrainConfig(
        widths=tuple(args.widths), train_scenes=args.train_scenes, val_scenes=args.val_scenes,
        scenarios=tuple(args.scenarios), steps=args.steps, scenes_per_step=args.scenes_per_step,
        lr=args.lr, pose_sigma_t=args.pose_sigma_t, pose_sigma_r=args.pose_sigma_r,
        seed=args.seed, threads=args.threads, workers=args.workers, device=args.device)
    command = "roco-env train-detector " + shlex.join(_argv_of(args))
    args.out.mkdir(parents=True, exist_ok=True)
    result = train(config, progress=not args.quiet, log=lambda m: print(m, file=sys.stderr))
    weights = args.out / SHIPPED_WEIGHTS
    save_checkpoint(weights, result.net.cpu(), config.grid, config.noise,
                    {"command": command, "seed": config.seed,
                     "train_config": result.summary()["config"],
                     "validation": result.validation})
    write_report(result, args.out, command, sha256_of(weights))
    print(f"wrote {weights} and the report in {args.out}")
    for key, value in result.validation.items():
        print(f"  {key}: {value:.3f}")
    return 0


def _argv_of(args: argparse.Namespace) -> list[str]:
    """Every option of this run, spelled out: the command that reproduces it."""
    return [f"--out={args.out}", f"--seed={args.seed}", f"--steps={args.steps}",
            f"--train-scenes={args.train_scenes}", f"--val-scenes={args.val_scenes}",
            f"--scenes-per-step={args.scenes_per_step}", f"--lr={args.lr}",
            "--widths", *map(str, args.widths), "--scenarios", *args.scenarios,
            f"--pose-sigma-t={args.pose_sigma_t}", f"--pose-sigma-r={args.pose_sigma_r}",
            f"--threads={args.threads}", f"--workers={args.workers}", f"--device={args.device}"]
