"""Privileged upper bounds of select and gate mode on the mixed benchmark (not shipped).

    nice -n 10 python baselines/learned_select/privileged_bound.py --out runs/bench_bound \
        [--noise 1.5 3.0] [--variants select choose gate]

Each variant is a select-mode policy that reads the privileged true relative poses
(info level ``full``) and runs every choice (identity / coalign / roco / roco_antialias,
own instances, each called every step like the env's stateful ones). Per filled slot it
measures each choice's pose error against the truth, e = max(translation m, rotation
deg), and acts:

* ``select``: the choice with the smallest e, or reject when every choice has e > 1;
* ``choose``: the choice with the smallest e, never reject;
* ``gate``: roco_antialias, or reject when its e > 1 (what gate mode over
  roco_antialias can reach at best).

It writes ``results.jsonl`` in the ``roco-env compare`` layout (the cells of the README's
grid, policy ``bound_<variant>``), so ``table.py`` reads it beside the other folders.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from roco_env.geometry import apply_correction, se2_compose, se2_inverse
from roco_env.policies import make_policy
from roco_env.policies.base import act
from roco_env.sweeps.cells import build_grid
from roco_env.sweeps.episode import run_episode

CHOICES = ("identity", "coalign", "roco", "roco_antialias")
REJECT_ERROR = 1.0  # m / deg: a pose off by more than this is rejected
VARIANTS = ("select", "choose", "gate")


def pose_errors(poses: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(n,) max(translation m, rotation deg) between each pose and the true one."""
    delta = se2_compose(poses, se2_inverse(truth))
    return np.maximum(np.hypot(delta[:, 0], delta[:, 1]), np.degrees(np.abs(delta[:, 2])))


class PrivilegedSelect:
    """A select-mode action from the choices' poses and the privileged truth."""

    env_overrides = {"action.mode": "select"}
    keeps_state = "runs the stateful roco_antialias every step"

    def __init__(self, variant: str) -> None:
        self.variant = variant
        self.aligners = [make_policy(name) for name in CHOICES]

    def reset(self) -> None:
        for aligner in self.aligners:
            aligner.reset()

    def __call__(self, observation: dict, info: dict) -> np.ndarray:
        truth = info["privileged"]["true_relative_poses"]
        reported = info["privileged"]["reported_relative_poses"]
        n = int(np.sum(observation["collab_mask"]))
        errors = np.stack([pose_errors(apply_correction(reported, act(aligner, observation,
                                                                      info)[0])[:n], truth[:n])
                           for aligner in self.aligners])  # (choices, n)
        action = np.full(len(observation["collab_mask"]), CHOICES.index("roco_antialias"))
        reject = len(CHOICES)
        if self.variant == "gate":
            action[:n] = np.where(errors[-1] > REJECT_ERROR, reject, action[:n])
            return action
        action[:n] = np.argmin(errors, axis=0)
        if self.variant == "select":
            action[:n] = np.where(errors.min(axis=0) > REJECT_ERROR, reject, action[:n])
        return action


def grid_parser(description: str, seeds: int) -> argparse.ArgumentParser:
    """The options of a script that writes cells of the README's grid: --out,
    --scenarios, --noise, --seeds (default ``seeds``), --steps."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--out", required=True)
    parser.add_argument("--scenarios", nargs="+",
                        default=["urban_intersection", "parking_lot", "v2xset_like"])
    parser.add_argument("--noise", nargs="+", type=float, default=[0.2, 0.8, 1.5, 3.0])
    parser.add_argument("--seeds", type=int, default=seeds)
    parser.add_argument("--steps", type=int, default=10)
    return parser


def main(argv: list[str] | None = None) -> None:
    parser = grid_parser(__doc__.splitlines()[0], seeds=3)
    parser.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS))
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cells = build_grid(args.scenarios, args.noise, ["roco_antialias"], list(range(args.seeds)),
                       args.steps)
    with (out / "results.jsonl").open("a") as sink:
        for variant in args.variants:
            for cell in cells:
                metrics, _ = run_episode(replace(cell, policy=f"bound_{variant}"),
                                         lambda v=variant: PrivilegedSelect(v))
                record = {"cell": {"scenario": cell.scenario, "noise": cell.noise,
                                   "policy": f"bound_{variant}", "seed": cell.seed,
                                   "overrides": {}}, "metrics": {"ap70": metrics["ap70"]}}
                sink.write(json.dumps(record) + "\n")
                sink.flush()
                print(variant, cell.scenario, cell.noise, cell.seed,
                      round(metrics["ap70"], 4), file=sys.stderr)


if __name__ == "__main__":
    main()
