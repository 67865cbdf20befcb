"""Score a policy under attack: one sweep cell played twice, with its attack and without.

A cell whose overrides set ``attack.*`` (the attack stage, docs/attacks.md) runs its
episode, then the same episode without the attack (every ``attack.*`` override left out:
the traffic, noise and detections are the same, the attack drawing from its own stream),
with the same policy spec. Scored over the **honest egos** only (the agents that do not
attack, read from the privileged truth; the same agents in both runs):

* ``ap30`` / ``ap50`` / ``ap70``: dataset AP under attack; ``ap70_clean``: the same
  egos' dataset AP@0.7 in the episode without the attack;
* ``attack_success``: the share of honest ego-steps whose per-step AP@0.7 falls by more
  than :data:`SUCCESS_DROP` (5 points) against the same ego and step without the attack
  (an undefined AP, no ground truth and no predictions, counts as 0, as in the reward);
* ``detection_rate``: the share of (honest ego, step, attacker slot) the policy
  rejected (``info["rejected"]``; a policy that cannot reject scores 0);
* ``honest_rejected``: the share of (honest ego, step, honest collaborator slot)
  rejected under attack; ``clean_rejected``: the same without the attack (a defence's
  false alarms in a clean episode).

Per-step values come from the infos (``ap70``, ``rejected``, ``evaluated_collaborators``
of the scored frame); the attackers are the env's attack stage's (privileged). A cell
without an attack is played once and scored the same way, every ego honest.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from roco_env.evaluation import info_frame_stats
from roco_env.metrics import DEFAULT_IOU_THRESHOLDS, APAccumulator
from roco_env.sweeps.episode import run_episode
from roco_env.sweeps.grid import Cell
from roco_env.sweeps.records import error_record, ok_record

SUCCESS_DROP = 0.05  # AP@0.7 points (as a share) an attack must remove from a step to succeed
ATTACK_PREFIX = "attack."


def is_attacked(cell: Cell) -> bool:
    """Whether the cell's overrides set an attack."""
    return any(key.startswith(ATTACK_PREFIX) and not (key == "attack.kind" and value == "none")
               for key, value in cell.overrides)


def clean_twin(cell: Cell) -> Cell:
    """The cell without its ``attack.*`` overrides: the same episode, nobody attacking."""
    return replace(cell, overrides=tuple((k, v) for k, v in cell.overrides
                                         if not k.startswith(ATTACK_PREFIX)))


@dataclass
class AttackTally:
    """Per honest ego and step of one episode: AP@0.7 and its frame; slot decisions."""

    attackers: set[str] | None = None
    ap70: dict[tuple[str, int], float] = field(default_factory=dict)
    ap: APAccumulator = field(default_factory=lambda: APAccumulator(DEFAULT_IOU_THRESHOLDS))
    rejected: dict[bool, list[bool]] = field(default_factory=lambda: {True: [], False: []})

    def on_step(self, step: int, env: Any, actions: dict, infos: dict) -> None:
        """``run_episode``'s step callback."""
        if self.attackers is None:
            self.attackers = {env.possible_agents[k] for k in env.pipeline.attack.attackers}
        for agent, info in infos.items():
            if agent in self.attackers or "frame_scores" not in info:
                continue
            self.ap70[agent, step] = max(float(info["ap70"]), 0.0)
            self.ap.add_stats(info_frame_stats(info))
            for slot, sender in enumerate(info["evaluated_collaborators"]):
                self.rejected[sender in self.attackers].append(bool(info["rejected"][slot]))

    def share_rejected(self, attackers: bool) -> float:
        values = self.rejected[attackers]
        return float(np.mean(values)) if values else float("nan")


def _played(cell: Cell, tally: AttackTally) -> tuple[dict, dict]:
    return run_episode(cell, on_step=tally.on_step)


def attack_metrics(cell: Cell,
                   play: Callable[[Cell, AttackTally], tuple[dict, dict]] = _played
                   ) -> tuple[dict[str, float], dict[str, list]]:
    """(metrics, samples) of a cell (see the module docstring); ``samples`` and the
    pose-error metrics are those of its own episode (every ego)."""
    attacked = AttackTally()
    metrics, samples = play(cell, attacked)
    clean = attacked
    if is_attacked(cell):
        clean = AttackTally(attackers=attacked.attackers)
        play(clean_twin(cell), clean)
    ap = attacked.ap.ap()
    metrics.update({"ap30": ap[0.3], "ap50": ap[0.5], "ap70": ap[0.7],
                    "ap70_clean": clean.ap.ap()[0.7]})
    drops = [clean.ap70[key] - value > SUCCESS_DROP for key, value in attacked.ap70.items()
             if key in clean.ap70]
    metrics["attack_success"] = float(np.mean(drops)) if drops else float("nan")
    metrics["detection_rate"] = attacked.share_rejected(True)
    metrics["honest_rejected"] = attacked.share_rejected(False)
    metrics["clean_rejected"] = clean.share_rejected(False)
    return metrics, samples


def run_attack_cell(cell: Cell) -> dict[str, Any]:
    """The stored record of one cell (a sweep's ``cell_fn``): attacked cells scored by
    :func:`attack_metrics`, the others (the clean rows of a table) as attacked cells
    would be without an attacker (every ego honest). An exception becomes an ``error``
    record."""
    start = time.perf_counter()
    try:
        metrics, samples = attack_metrics(cell)
    except Exception as exc:  # noqa: BLE001 - a failing cell is recorded, the sweep goes on
        return error_record(cell, exc, time.perf_counter() - start)
    return ok_record(cell, metrics, samples, time.perf_counter() - start)
