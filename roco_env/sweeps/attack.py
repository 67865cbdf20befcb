"""Score a policy under attack: a sweep cell played with its attack and without it.

A cell whose overrides set ``attack.*`` (the attack stage, docs/attacks.md) is played,
and so is its clean twin (every ``attack.*`` override left out: the same traffic, noise
and detections, the attack drawing from its own stream) with the same policy spec. Both
are scored over the cell's **honest egos** (the agents that do not attack; the env's
attack stage names them, privileged), ego by ego and step by step:

* ``ap30`` / ``ap50`` / ``ap70``: dataset AP under attack; ``ap70_clean``: the same
  egos' dataset AP@0.7 in the clean twin;
* ``attack_success``: the share of honest ego-steps whose per-step AP@0.7 falls by more
  than 5 points against the same ego and step of the clean twin
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
from dataclasses import replace
from typing import Any

from roco_env.attacks.scoring import EpisodeLog, attack_scores
from roco_env.sweeps.cells import Cell
from roco_env.sweeps.episode import run_episode
from roco_env.sweeps.records import error_record, ok_record

ATTACK_PREFIX = "attack."


def is_attacked(cell: Cell) -> bool:
    """Whether the cell's overrides set an attack (``attack.kind`` other than none)."""
    kind = dict(cell.overrides).get("attack.kind", "none")
    return kind != "none"


def clean_twin(cell: Cell) -> Cell:
    """The cell without its ``attack.*`` overrides: the same episode, nobody attacking."""
    return replace(cell, overrides=tuple((k, v) for k, v in cell.overrides
                                         if not k.startswith(ATTACK_PREFIX)))


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
    metrics.update(attack_scores(log, clean))
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
