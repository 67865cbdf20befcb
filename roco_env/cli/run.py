"""``roco-env run``: one episode with one policy, a per-step metrics table and the totals.

Per step (over every evaluated agent): mean per-frame AP@0.5/0.7 (%), median relative
pose error of the collaborator slots before and after the policy's correction (m / deg),
GT and prediction counts, and how many agents' actions changed a reported pose.
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from roco_env.evaluation import UNDEFINED, filled_rpe_rows
from roco_env.sweeps.episode import run_episode
from roco_env.sweeps.options import add_episode_options, episode_cell
from roco_env.sweeps.stats import nanmean

COLUMNS = ("step", "AP@0.5", "AP@0.7", "RPE t before", "RPE t after", "RPE r before",
           "RPE r after", "GT", "pred", "moved")
WIDTHS = (5, 7, 7, 13, 12, 13, 12, 5, 5, 6)


def _fmt(value: float, digits: int) -> str:
    return "-" if not math.isfinite(value) else f"{value:.{digits}f}"


def _median(infos: dict, key: str, column: int) -> float:
    rows = [filled_rpe_rows(i[key]) for i in infos.values() if key in i]
    values = np.concatenate(rows)[:, column] if rows else np.zeros(0)
    return float(np.median(values)) if values.size else math.nan


def step_row(step: int, actions: dict, infos: dict) -> list[str]:
    """The table cells of one step."""
    ap50 = nanmean([i["ap50"] for i in infos.values() if i.get("ap50", UNDEFINED) != UNDEFINED])
    ap70 = nanmean([i["ap70"] for i in infos.values() if i.get("ap70", UNDEFINED) != UNDEFINED])
    moved = sum(bool(np.any(np.abs(a) > 1e-9)) for a in actions.values())
    return [str(step), _fmt(100 * ap50, 1), _fmt(100 * ap70, 1),
            _fmt(_median(infos, "rpe_before", 0), 3), _fmt(_median(infos, "rpe_after", 0), 3),
            _fmt(_median(infos, "rpe_before", 1), 3), _fmt(_median(infos, "rpe_after", 1), 3),
            str(sum(int(i.get("n_gt", 0)) for i in infos.values())),
            str(sum(int(i.get("n_pred", 0)) for i in infos.values())),
            f"{moved}/{len(actions)}"]


def _line(cells: list[str] | tuple[str, ...]) -> str:
    return "  ".join(c.rjust(w) for c, w in zip(cells, WIDTHS, strict=True))


def run(args: argparse.Namespace) -> int:
    cell = episode_cell(args)

    def on_step(step: int, env, actions: dict, infos: dict) -> None:
        if step == 1:  # printed once a step ran, so that a scene that fails says why alone
            print(f"{cell.scenario}: policy {cell.policy}, noise {cell.noise:g} m / "
                  f"{cell.noise:g} deg, {cell.steps} steps, seed {cell.seed}")
            print(_line(COLUMNS), flush=True)
        print(_line(step_row(step, actions, infos)), flush=True)

    metrics, _ = run_episode(cell, on_step=on_step)
    if metrics["steps"] < cell.steps:
        print(f"the episode ended after {metrics['steps']} of {cell.steps} steps: the scenario's "
              "frames ran out (a replay or user frames end at their last frame)")
    print(f"dataset AP@0.3 {_fmt(100 * metrics['ap30'], 1)}  AP@0.5 {_fmt(100 * metrics['ap50'], 1)}"
          f"  AP@0.7 {_fmt(100 * metrics['ap70'], 1)} (%)")
    print(f"RPE after: t median {_fmt(metrics['rpe_t_median'], 3)} m, p95 "
          f"{_fmt(metrics['rpe_t_p95'], 3)} m; r median {_fmt(metrics['rpe_r_median'], 3)} deg, p95 "
          f"{_fmt(metrics['rpe_r_p95'], 3)} deg; Success@1m1deg "
          f"{_fmt(100 * metrics['success1'], 1)}% (before {_fmt(100 * metrics['success1_before'], 1)}%)")
    print(f"matching P/R {_fmt(100 * metrics['match_precision'], 1)}% / "
          f"{_fmt(100 * metrics['match_recall'], 1)}%; corrected in "
          f"{_fmt(100 * metrics['correction_share'], 1)}% of frames")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("run", help="run one episode and print per-step metrics",
                                   description=__doc__,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    add_episode_options(parser, steps=20)
    parser.set_defaults(func=run)
