"""``roco-env train-detector``: train the learned BEV detector and write weights + report.

Its options are :class:`~roco_env.training.train.TrainConfig`'s fields (``--pose-sigma-t``
for ``pose_sigma_t``), generated from the dataclass, plus ``--out`` and ``--quiet``.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

from roco_env.flags import SpecFlags


def _flags() -> SpecFlags:
    """The options of TrainConfig; ``--freeze-encoder`` / ``--freeze-detector`` are the
    older names of ``--no-train-encoder`` / ``--no-train-detector``."""
    from roco_env.training.train import WHERE, TrainConfig

    return SpecFlags(TrainConfig, WHERE, aliases={"--freeze-encoder": ("train_encoder", False),
                                                  "--freeze-detector": ("train_detector", False)})


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "train-detector",
        help="train the learned BEV detector in the simulator (weights + report)",
        description="Generate training scenes from the scenario library (seeds disjoint from "
        "evaluation seeds), train the learned BEV detector deterministically, and write "
        "OUT/bev_detector.pt, OUT/report.md, OUT/report.json, OUT/loss_curves.png and "
        "OUT/loss_history.json (the per-step losses it draws).",
    )
    p.add_argument("--out", required=True, type=Path, help="output folder")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    _flags().add_to(p)
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from roco_env.sensing.learned.model import WEIGHTS_FILE, save_checkpoint, sha256_of
    from roco_env.training.detector_report import write_report
    from roco_env.training.train import init_checkpoint, train

    flags = _flags()
    config = flags.parse(args)
    command = "roco-env train-detector " + shlex.join([f"--out={args.out}",
                                                       *flags.argv(config)])
    # Checked (and hashed: the output may overwrite it) before any output or scene exists.
    init_sha256 = None if init_checkpoint(config) is None else sha256_of(config.init)
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
