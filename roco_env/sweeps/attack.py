"""Score a policy under attack: a sweep cell played with its attack and without it.

A cell is played; when its env reports attackers (the env's attack stage, privileged:
set by the cell's ``attack.*`` overrides or by its scenario file, docs/attacks.md), so is
its clean twin (:func:`clean_twin`: nobody attacking, the same traffic, noise and
detections, the attack drawing from its own stream) with the same policy spec. Both are
scored over the cell's **honest egos** (the agents that do not attack), ego by ego and
step by step:

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

A cell whose env reports no attacker is scored the same way on its own episode (every
ego honest, ``ap70_clean`` = ``ap70``). An episode without attackers is played once per
process (:func:`play`): the clean twin of a (scenario, policy, seed) serves the cells of
all its attacks, and the cell without an attack is that twin.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any, NamedTuple

from roco_env.attacks.scoring import EpisodeLog, attack_scores
from roco_env.scenario import load_scenario
from roco_env.sweeps.cells import Cell
from roco_env.sweeps.episode import run_cell, timed_episode

ATTACK_PREFIX = "attack."
CLEAN_CACHE_SIZE = 64  # clean episodes kept per process (a protocol worker needs ~32)


class Played(NamedTuple):
    """One played cell: :func:`timed_episode`'s metrics, samples and median time per
    call (ms), and its :class:`EpisodeLog`."""

    metrics: dict[str, float]
    samples: dict[str, list]
    per_call_ms: float
    log: EpisodeLog


_clean: dict[str, Played] = {}  # the clean episodes played in this process, by cell key


def clean_twin(cell: Cell) -> Cell:
    """The cell with nobody attacking: its ``attack`` overrides left out and, where its
    scenario file itself sets an attack, ``attack.kind: none`` (and no parameters)."""
    kept = tuple((k, v) for k, v in cell.overrides
                 if k != "attack" and not k.startswith(ATTACK_PREFIX))
    twin = replace(cell, overrides=kept)
    if load_scenario(twin.scenario, **twin.env_overrides()).attack.kind == "none":
        return twin
    return replace(twin, overrides=tuple(sorted(
        kept + (("attack.kind", "none"), ("attack.params", {})), key=lambda item: item[0])))


def play(cell: Cell) -> Played:
    """The cell's episode (:func:`timed_episode`) and its log; an episode without
    attackers is played once per process (episodes are deterministic)."""
    if cell.key in _clean:
        return _clean[cell.key]
    log = EpisodeLog()
    played = Played(*timed_episode(cell, on_step=log.on_step), log)
    if not log.attackers:
        if len(_clean) >= CLEAN_CACHE_SIZE:
            del _clean[next(iter(_clean))]  # the oldest
        _clean[cell.key] = played
    return played


def attack_metrics(cell: Cell) -> tuple[dict[str, float], dict[str, list], float]:
    """(metrics, samples, median time per call ms) of a cell (module docstring);
    ``samples``, the time and the pose-error metrics are those of its own episode (every
    ego)."""
    played = play(cell)
    clean = play(clean_twin(cell)).log if played.log.attackers else played.log
    return {**played.metrics, **attack_scores(played.log, clean)}, played.samples, \
        played.per_call_ms


def run_attack_cell(cell: Cell) -> dict[str, Any]:
    """The stored record of one cell scored by :func:`attack_metrics` (a sweep's
    ``cell_fn``: :func:`~roco_env.sweeps.episode.run_cell` with that score)."""
    return run_cell(cell, attack_metrics)
