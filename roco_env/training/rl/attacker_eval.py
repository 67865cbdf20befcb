"""The learned attacker's held-out evaluations and its report
(:mod:`roco_env.training.rl.attacker`).

An evaluation plays held-out seeds with an action function (the greedy policy, or the
zero action) and scores each episode against its clean twin
(:func:`roco_env.attacks.scoring.attack_scores`, over the honest egos). The issue's
question is how much AP@0.7 an attacker removes while its detection rate stays under
:data:`STEALTH`: :func:`best_stealthy` answers it over the evaluations of one training
run. :func:`write_report` writes the run's ``report.json``, ``curve.csv`` (the training
curve), ``evaluations.csv`` and ``curve.png``.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from roco_env.attacks.scoring import attack_scores

if TYPE_CHECKING:
    from roco_env.training.rl.attacker import AttackerEnv

__all__ = ["CURVE", "EVALUATION", "STEALTH", "best_stealthy", "evaluate", "write_report"]

STEALTH = 0.10  # the detection rate (share of attacker slots rejected) a stealthy attack stays under
CURVE = ("timesteps", "return", "return_sd", "wall_s")  # curve.csv's columns
EVALUATION = ("timesteps", "removed", "removed_sd", "ap70", "ap70_clean", "attack_success",
              "detection_rate", "honest_rejected", "clean_rejected", "wall_s")  # evaluations.csv


def evaluate(env: AttackerEnv, act: Callable[[np.ndarray], np.ndarray],
             seeds: Sequence[int]) -> dict[str, float]:
    """The attack scores (:func:`roco_env.attacks.scoring.attack_scores`: shares in [0, 1]),
    mean over the ``seeds`` episodes of ``env``, of ``act`` (flat observation -> action)
    against their clean twins (:meth:`AttackerEnv.clean_log`), with ``removed`` and
    ``removed_sd``: the AP@0.7 points (0-100) removed, mean and sample standard deviation
    over the episodes (NaN for one episode)."""
    rows = []
    for seed in seeds:
        observation, _ = env.reset(seed=seed)
        done = False
        while not done:
            observation, _, terminated, truncated, _ = env.step(act(observation))
            done = terminated or truncated
        rows.append(attack_scores(env.log, env.clean_log(seed)))
    scores = {key: float(np.nanmean([row[key] for row in rows])) for key in rows[0]}
    removed = [100.0 * (row["ap70_clean"] - row["ap70"]) for row in rows]
    scores["removed"] = float(np.mean(removed))
    scores["removed_sd"] = float(np.std(removed, ddof=1)) if len(removed) > 1 else float("nan")
    return scores


def best_stealthy(evaluations: Sequence[dict[str, Any]]) -> dict[str, Any] | None:
    """The evaluation (a row of :func:`evaluate` with its ``timesteps``) that removes the
    most AP@0.7 among those detected in under :data:`STEALTH` of the attacker's slots
    (the earliest of equals); None if none is."""
    stealthy = [row for row in evaluations if row["detection_rate"] < STEALTH]
    return max(stealthy, key=lambda row: row["removed"], default=None)


def write_report(out: Path, report: dict[str, Any]) -> None:
    """``report.json``, ``curve.csv`` (``report["curve"]``), ``evaluations.csv``
    (``report["evaluations"]``) and ``curve.png`` (the training return, and per evaluation
    the points removed and the detection rate) into the folder ``out``."""
    (out / "report.json").write_text(json.dumps(report, indent=2), encoding="utf-8")
    for name, columns, rows in (("curve.csv", CURVE, report["curve"]),
                                ("evaluations.csv", EVALUATION, report["evaluations"])):
        with (out / name).open("w", newline="", encoding="utf-8") as handle:
            writer = csv.DictWriter(handle, fieldnames=columns, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(rows)
    import matplotlib.pyplot as plt

    figure, (train, held) = plt.subplots(1, 2, figsize=(10, 3.4))
    steps = np.array([p["timesteps"] for p in report["curve"]])
    mean = np.array([p["return"] for p in report["curve"]])
    spread = np.array([p["return_sd"] for p in report["curve"]])
    train.plot(steps, mean, marker="o", markersize=3)
    train.fill_between(steps, mean - spread, mean + spread, alpha=0.2)
    train.set_xlabel("env steps")
    train.set_ylabel(f"episode return ({report['reward']}), mean +- sd")
    train.set_title(f"training vs {report['victims']}")
    evals = report["evaluations"]
    at = [row["timesteps"] for row in evals]
    held.errorbar(at, [row["removed"] for row in evals],
                  yerr=[row["removed_sd"] for row in evals], marker="o", capsize=3,
                  label="AP@0.7 removed (points)")
    held.plot(at, [100.0 * row["detection_rate"] for row in evals], marker="s",
              label="detected (% of its slots)")
    held.axhline(100.0 * STEALTH, color="grey", linestyle=":", label=f"{STEALTH:.0%} detected")
    held.set_xlabel("env steps")
    held.set_title(f"greedy, {report['eval_episodes']} held-out episodes")
    held.legend(fontsize=7)
    for axis in (train, held):
        axis.grid(alpha=0.3)
    figure.tight_layout()
    figure.savefig(out / "curve.png", dpi=120)
    plt.close(figure)
