"""An evaluation's objective: larger is always worse for the policy (the search maximises).

One evaluation runs the scenario for each seed (one episode of ``steps`` steps per
seed, the sweep episode runner :func:`roco_env.sweeps.episode.run_episode`) and pools:

* ``harm``: share in [0, 1] of the collaborator poses the policy made more than
  :data:`roco_env.metrics.HARM_MARGIN` = 0.5 m worse than reported (translation error after
  > before + 0.5 m, :func:`roco_env.metrics.harm_share`),
  over every filled collaborator slot of every evaluated agent, step and seed;
* ``success``: minus Success@1m1deg after the correction (so maximising it finds the
  scenes where the fewest poses end within 1 m and 1 deg), in [-1, 0];
* ``ap70``: minus the dataset AP@0.7 of the fused detections, mean over seeds, in [-1, 0];
* ``gap``: the oracle's AP@0.7 minus the policy's on the same scene and seeds, in [-1, 1].

A scene without collaborator pairs (harm, success) or without an AP (no ground truth)
has no objective: :class:`Infeasible` is raised and the search records why.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from roco_env.metrics import harm_share, success_rate
from roco_env.sweeps.cells import Cell
from roco_env.sweeps.episode import run_episode

OBJECTIVES = ("harm", "success", "ap70", "gap")


class Infeasible(ValueError):
    """The scenario has no value of the objective (no collaborator pairs, no AP)."""


@dataclass(frozen=True)
class Evaluation:
    """The objective ``value`` and the pooled metrics behind it (harm, success1, ap70,
    pairs, frames; oracle_ap70 for ``gap``)."""

    value: float
    metrics: dict[str, float] = field(default_factory=dict)


def check_objective(objective: str) -> str:
    if objective not in OBJECTIVES:
        raise ValueError(f"objective={objective!r} is not allowed; choose one of {list(OBJECTIVES)}")
    return objective


def _pooled(scenario: str, policy: str, seeds: Sequence[int], steps: int) -> dict[str, float]:
    befores, afters, ap70, frames = [], [], [], 0
    for seed in seeds:
        metrics, samples = run_episode(Cell(scenario, None, policy, int(seed), int(steps)))
        befores.append(np.reshape(samples["before"], (-1, 2)))
        afters.append(np.reshape(samples["after"], (-1, 2)))
        ap70.append(metrics["ap70"])
        frames += int(metrics["frames"])
    before, after = np.concatenate(befores), np.concatenate(afters)
    finite_ap = [a for a in ap70 if math.isfinite(a)]
    return {
        "harm": harm_share(before, after),
        "success1": success_rate(after, 1.0) if after.shape[0] else float("nan"),
        "ap70": float(np.mean(finite_ap)) if finite_ap else float("nan"),
        "pairs": int(after.shape[0]),
        "frames": frames,
    }


def evaluate(scenario: str, policy: str, objective: str, seeds: Sequence[int],
             steps: int) -> Evaluation:
    """Run ``policy`` on ``scenario`` (name or YAML path, its own noise) for each seed and
    return the objective (see the module docstring). Deterministic in its arguments."""
    check_objective(objective)
    if not seeds:
        raise ValueError("seeds must not be empty")
    metrics = _pooled(scenario, policy, seeds, steps)
    if objective == "harm":
        value = metrics["harm"]
    elif objective == "success":
        value = -metrics["success1"]
    elif objective == "ap70":
        value = -metrics["ap70"]
    else:
        metrics["oracle_ap70"] = _pooled(scenario, "oracle", seeds, steps)["ap70"]
        value = metrics["oracle_ap70"] - metrics["ap70"]
    if not math.isfinite(value):
        why = "no collaborator pairs" if metrics["pairs"] == 0 else "no AP (no ground truth)"
        raise Infeasible(f"objective {objective!r} is undefined on this scenario: {why}")
    return Evaluation(float(value), metrics)
