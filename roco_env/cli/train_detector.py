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
        "OUT/bev_detector.pt, OUT/report.md, OUT/report.json, OUT/loss_curves.png and "
        "OUT/loss_history.json (the per-step losses it draws).",
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
    p.add_argument("--fused-x-range", type=float, nargs=2, metavar=("LOW", "HIGH"),
                   help="ego-frame x extent (m) the fused loss decodes: the detector grid grown "
                   "to cover it in whole feature cells, e.g. the evaluation range -140.8 140.8 "
                   "(default: the detector grid)")
    p.add_argument("--fused-y-range", type=float, nargs=2, metavar=("LOW", "HIGH"),
                   help="the same along y (default: the detector grid)")
    p.add_argument("--init", type=Path, metavar="FILE",
                   help="weights file to start from; its widths must be --widths (default: "
                   "random initialisation; --lr applies as given)")
    p.add_argument("--freeze-encoder", action="store_true",
                   help="train the trunk and heads only (needs --init): a fine-tuning stage "
                   "that keeps every encoder map as it was")
    p.add_argument("--fusion", choices=("max", "gated"), default=d.fusion,
                   help="intermediate fusion of the fused loss and of the weights: the maximum, "
                   "or the maximum after a learned per-cell gate on each collaborator's map "
                   "(default %(default)s)")
    p.add_argument("--freeze-detector", action="store_true",
                   help="train the fusion gate only (needs --init and --fusion gated): every "
                   "detection of the start weights stays as it was")
    p.add_argument("--warp-augment", type=float, default=d.warp_augment, metavar="P",
                   help="share in [0, 1] of single-agent maps decoded after a random rigid "
                   "warp (any heading, a shift of up to one feature cell), so the network "
                   "learns maps that survive the warp of fusion (default %(default)s)")
    p.add_argument("--threads", type=int, default=d.threads,
                   help="torch CPU threads (default %(default)s)")
    p.add_argument("--workers", type=int, default=d.workers,
                   help="processes generating scenes and batches (default %(default)s: none; "
                   "the weights do not depend on it)")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from roco_env.sensing.learned.model import WEIGHTS_FILE, save_checkpoint, sha256_of
    from roco_env.training.report import write_report
    from roco_env.training.train import TrainConfig, init_checkpoint, train

    config = TrainConfig(
        widths=tuple(args.widths), train_scenes=args.train_scenes, val_scenes=args.val_scenes,
        scenarios=tuple(args.scenarios), steps=args.steps, scenes_per_step=args.scenes_per_step,
        lr=args.lr, pose_sigma_t=args.pose_sigma_t, pose_sigma_r=args.pose_sigma_r,
        fused_x_range=_pair(args.fused_x_range), fused_y_range=_pair(args.fused_y_range),
        init=None if args.init is None else str(args.init),
        train_encoder=not args.freeze_encoder, fusion=args.fusion,
        train_detector=not args.freeze_detector, warp_augment=args.warp_augment,
        seed=args.seed, threads=args.threads, workers=args.workers, device=args.device)
    command = "roco-env train-detector " + shlex.join(_argv_of(args))
    # Checked (and hashed: the output may overwrite it) before any output or scene exists.
    init_sha256 = None if init_checkpoint(config) is None else sha256_of(args.init)
    init = {} if init_sha256 is None else {"init_sha256": init_sha256}
    args.out.mkdir(parents=True, exist_ok=True)
    result = train(config, progress=not args.quiet, log=lambda m: print(m, file=sys.stderr))
    weights = args.out / WEIGHTS_FILE
    save_checkpoint(weights, result.net.cpu(), config.grid, config.noise,
                    {"command": command, "seed": config.seed, **init,
                     "train_config": result.summary()["config"],
                     "validation": result.validation})
    write_report(result, args.out, command, sha256_of(weights), init_sha256)
    print(f"wrote {weights} and the report in {args.out}")
    for key, value in result.validation.items():
        print(f"  {key}: {value:.3f}")
    return 0


def _pair(values: list[float] | None) -> tuple[float, float] | None:
    return None if values is None else (values[0], values[1])


def _argv_of(args: argparse.Namespace) -> list[str]:
    """Every option of this run, spelled out: the command that reproduces it."""
    optional = [*(["--fused-x-range", *map(str, args.fused_x_range)] if args.fused_x_range
                  else []),
                *(["--fused-y-range", *map(str, args.fused_y_range)] if args.fused_y_range
                  else []),
                *([f"--init={args.init}"] if args.init else []),
                *(["--freeze-encoder"] if args.freeze_encoder else []),
                *([f"--fusion={args.fusion}"] if args.fusion != "max" else []),
                *(["--freeze-detector"] if args.freeze_detector else []),
                *([f"--warp-augment={args.warp_augment}"] if args.warp_augment else [])]
    return [f"--out={args.out}", f"--seed={args.seed}", f"--steps={args.steps}",
            f"--train-scenes={args.train_scenes}", f"--val-scenes={args.val_scenes}",
            f"--scenes-per-step={args.scenes_per_step}", f"--lr={args.lr}",
            "--widths", *map(str, args.widths), "--scenarios", *args.scenarios,
            f"--pose-sigma-t={args.pose_sigma_t}", f"--pose-sigma-r={args.pose_sigma_r}",
            *optional, f"--threads={args.threads}", f"--workers={args.workers}",
            f"--device={args.device}"]
