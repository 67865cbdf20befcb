"""``roco-env render``: an episode's bird's-eye view as PNG frames and/or an animated GIF.

Each step's ``env.render()`` (rgb_array: ground truth, every agent's boxes in its
colour, fused boxes, true and reported poses, the ego's evaluation range; the
title names the policy, scenario, step, ego and pose noise) becomes
``OUT/frame_0001.png`` ... and, with ``--gif``, one frame of the GIF. Frames are
written as they are drawn (none is kept), so memory does not grow with ``--steps``.
"""

from __future__ import annotations

import argparse
from contextlib import nullcontext
from pathlib import Path

import numpy as np
from PIL import Image

from roco_env.render import GifStream
from roco_env.sweeps.cells import Cell
from roco_env.sweeps.episode import run_episode
from roco_env.sweeps.options import add_episode_options, episode_cell


def _frame(env) -> Image.Image:
    picture = np.asarray(env.render())
    if picture.ndim != 3 or picture.shape[2] not in (3, 4):
        raise ValueError(f"env.render() must return an (H, W, 3) image; got shape {picture.shape}")
    return Image.fromarray(picture.astype(np.uint8)[..., :3])


def render_episode(cell: Cell, out: Path | None = None, gif: str | Path | None = None,
                   fps: float = 5.0, ego: str | None = None) -> tuple[int, dict]:
    """Run ``cell`` and write each step's picture as ``out/frame_NNNN.png`` and/or one
    frame of the GIF ``gif`` (streamed); returns (frames written, the episode's metrics).
    ``ego``: the agent whose fused boxes are drawn (None: the first evaluated one)."""
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
    written = 0

    with GifStream(gif, fps) if gif is not None else nullcontext() as stream:
        def on_step(step: int, env, actions: dict, infos: dict) -> None:
            nonlocal written
            if ego is not None:
                env.render_ego = ego  # ValueError naming the agents when unknown
            env.render_caption = f"policy {cell.policy}"
            frame = _frame(env)
            if out is not None:
                frame.save(out / f"frame_{step:04d}.png")
            if stream is not None:
                stream.append(frame)
            written += 1

        metrics, _ = run_episode(cell, on_step=on_step, render_mode="rgb_array")
    return written, metrics


def run(args: argparse.Namespace) -> int:
    if args.out is None and args.gif is None:
        raise ValueError("give --out DIR (PNG frames), --gif FILE.gif, or both")
    if args.fps <= 0:
        raise ValueError(f"--fps must be > 0; got {args.fps}")
    if args.gif is not None and Path(args.gif).suffix.lower() != ".gif":
        raise ValueError(f"--gif must name a .gif file; got {args.gif}")
    cell = episode_cell(args)
    out = Path(args.out) if args.out else None
    written, metrics = render_episode(cell, out, args.gif, args.fps, args.ego)
    if out is not None:
        print(f"wrote {written} PNG frames to {out}/")
    if args.gif is not None:
        print(f"wrote {args.gif} ({written} frames, {args.fps:g} fps)")
    print(f"dataset AP@0.7 {100 * metrics['ap70']:.1f}%")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("render", help="render an episode to PNG frames or a GIF",
                                   description=__doc__,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    add_episode_options(parser, steps=10)
    parser.add_argument("--out", default=None, metavar="DIR", help="folder for PNG frames")
    parser.add_argument("--gif", default=None, metavar="FILE", help="animated GIF to write")
    parser.add_argument("--ego", default=None, metavar="AGENT",
                        help="agent whose fused boxes are drawn (default: the first evaluated "
                        "one, e.g. cav_0)")
    parser.add_argument("--fps", type=float, default=5.0, help="GIF frame rate (default: 5)")
    parser.set_defaults(func=run)
