"""Score a policy under attack: a sweep cell played with its attack and without it.

A cell whose overrides set ``attack.*`` (the attack stage, docs/attacks.md) is played,
and so is its clean twin (every ``attack.*`` override left out: the same traffic, noise
and detections, the attack drawing from its own stream) with the same policy spec. Both
are scored over the cell's **honest egos** (the agents that do not attack; the env's
attack stage names them, privileged), ego by ego and step by step:

* ``ap30`` / ``ap50`` / ``ap70``: dataset AP under attack; ``ap70_clean``: the same
  egos' dataset AP@0.7 in the clean twin;
* ``attack_success``: the share of honest ego-steps whose per-step AP@0.7 falls by more
  than :data:`SUCCESS_DROP` (5 points) against the same ego and step of the clean twin
  (an undefined AP, no ground truth and no predictions, counts as 0, as in the reward);
* ``detection_rate``: the share of (honest ego, step, attacker slot) rejected
  (``info["rejected"]``; a policy that cannot reject scores 0);
* ``honest_rejected``: the share of (honest ego, step, honest collaborator slot)
  rejected under attack; ``clean_rejected``: the same in the clean twin (a defence's
  false alarms without an attacker).

A cell without an attack is scored the same way on its own episode (every ego honest,
``ap70_clean`` = ``ap70``). The clean twin of a (scenario, policy, seed) is played once
per process and reused by the cells of its attacks (:func:`clean_log`).
"""

from __future__ import annotations

import functools
import time
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from roco_env.evaluation import info_frame_stats
from roco_env.metrics import DEFAULT_IOU_THRESHOLDS, APAccumulator, FrameStats
from roco_env.sweeps.episode import run_episode
from roco_env.sweeps.grid import Cell
from roco_env.sweeps.records import error_record, ok_record

SUCCESS_DROP = 0.05  # AP@0.7 (as a share) an attack must remove from an ego-step to succeed
ATTACK_PREFIX = "attack."
ATTACK_METRICS = ("ap70_clean", "attack_success", "detection_rate", "honest_rejected",
                  "clean_rejected")


def is_attacked(cell: Cell) -> bool:
    """Whether the cell's overrides set an attack (``attack.kind`` other than none)."""
    kind = dict(cell.overrides).get("attack.kind", "none")
    return kind != "none"


def clean_twin(cell: Cell) -> Cell:
    """The cell without its ``attack.*`` overrides: the same episode, nobody attacking."""
    return replace(cell, overrides=tuple((k, v) for k, v in cell.overrides
                                         if not k.startswith(ATTACK_PREFIX)))


@dataclass
class EpisodeLog:
    """One episode, ego by ego: its attackers (agent ids), per (agent, step) AP@0.7
    (undefined = 0), each agent's scored frames, and every (ego, sender, rejected)
    decision on a filled slot of a scored frame."""

    attackers: frozenset[str] = frozenset()
    ap70: dict[tuple[str, int], float] = field(default_factory=dict)
    frames: dict[str, list[FrameStats]] = field(default_factory=dict)
    decisions: list[tuple[str, str, bool]] = field(default_factory=list)

    def on_step(self, step: int, env: Any, actions: dict, infos: dict) -> None:
        """``run_episode``'s step callback."""
        self.attackers = frozenset(env.possible_agents[k] for k in env.pipeline.attack.attackers)
        for agent, info in infos.items():
            if "frame_scores" not in info:  # not evaluated
                continue
            self.ap70[agent, step] = max(float(info["ap70"]), 0.0)
            self.frames.setdefault(agent, []).append(info_frame_stats(info))
            self.decisions += [(agent, sender, bool(info["rejected"][slot]))
                               for slot, sender in enumerate(info["evaluated_collaborators"])]

    def ap(self, egos: Iterable[str]) -> dict[float, float]:
        """Dataset AP by IoU threshold over the frames of ``egos``."""
        accumulator = APAccumulator(DEFAULT_IOU_THRESHOLDS)
        for ego in egos:
            for stats in self.frames.get(ego, []):
                accumulator.add_stats(stats)
        return accumulator.ap()

    def rejected(self, egos: frozenset[str], attackers: frozenset[str],
                 of_attackers: bool) -> float:
        """The share of the decisions of ``egos`` on attackers' (or honest) slots that
        rejected; NaN without any."""
        values = [rejected for ego, sender, rejected in self.decisions
                  if ego in egos and (sender in attackers) == of_attackers]
        return float(np.mean(values)) if values else float("nan")


def play(cell: Cell) -> tuple[dict, dict, EpisodeLog]:
    """(metrics, samples, log) of the cell's episode (:func:`run_episode`)."""
    log = EpisodeLog()
    metrics, samples = run_episode(cell, on_step=log.on_step)
    return metrics, samples, log


@functools.lru_cache(maxsize=64)
def clean_log(cell: Cell) -> EpisodeLog:
    """The log of a clean cell, played once per process (episodes are deterministic)."""
    return play(cell)[2]


def attack_metrics(cell: Cell) -> tuple[dict[str, float], dict[str, list]]:
    """(metrics, samples) of a cell (module docstring); ``samples`` and the pose-error
    metrics are those of its own episode (every ego)."""
    metrics, samples, log = play(cell)
    clean = clean_log(clean_twin(cell)) if is_attacked(cell) else log
    honest = frozenset(log.frames) - log.attackers
    ap = log.ap(honest)
    metrics.update({"ap30": ap[0.3], "ap50": ap[0.5], "ap70": ap[0.7],
                    "ap70_clean": clean.ap(honest)[0.7]})
    drops = [clean.ap70[key] - value > SUCCESS_DROP for key, value in log.ap70.items()
             if key[0] in honest and key in clean.ap70]
    metrics["attack_success"] = float(np.mean(drops)) if drops else float("nan")
    metrics["detection_rate"] = log.rejected(honest, log.attackers, True)
    metrics["honest_rejected"] = log.rejected(honest, log.attackers, False)
    metrics["clean_rejected"] = clean.rejected(honest, log.attackers, False)
    return metrics, samples


def run_attack_cell(cell: Cell) -> dict[str, Any]:
    """The stored record of one cell (a sweep's ``cell_fn``, module-level so process pools
    ship it), scored by :func:`attack_metrics`; an exception becomes an ``error`` record."""
    start = time.perf_counter()
    try:
        metrics, samples = attack_metrics(cell)
    except Exception as exc:  # noqa: BLE001 - a failing cell is recorded, the sweep goes on
        return error_record(cell, exc, time.perf_counter() - start)
    return ok_record(cell, metrics, samples, time.perf_counter() - start)
