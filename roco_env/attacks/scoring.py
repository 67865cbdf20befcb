"""What an episode under attack did to its honest egos, ego by ego and step by step.

:class:`EpisodeLog` collects, from the infos of every step (``ap70``, the frame's AP
input, ``rejected`` and ``evaluated_collaborators`` of the scored frame) and the env's
attack stage (who attacks: privileged), what the attack metrics need
(:mod:`roco_env.sweeps.attack`; the learned attacker's evaluation,
:mod:`roco_env.training.rl.attacker`).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from roco_env.evaluation import info_frame_stats
from roco_env.metrics import DEFAULT_IOU_THRESHOLDS, APAccumulator, FrameStats

__all__ = ["ATTACK_METRICS", "SUCCESS_DROP", "EpisodeLog", "attack_scores"]

SUCCESS_DROP = 0.05  # AP@0.7 (as a share) an attack must remove from an ego-step to succeed
ATTACK_METRICS = ("ap70_clean", "attack_success", "detection_rate", "honest_rejected",
                  "clean_rejected")


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
        """``run_episode``'s step callback: the env's attackers, then :meth:`record`."""
        self.attackers = frozenset(env.possible_agents[k] for k in env.pipeline.attack.attackers)
        self.record(step, infos)

    def record(self, step: int, infos: dict) -> None:
        """Step ``step``'s infos (by agent; full info level) of the env's agents."""
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


def attack_scores(log: EpisodeLog, clean: EpisodeLog) -> dict[str, float]:
    """An attacked episode's scores against its clean twin, over its honest egos: ``ap30`` /
    ``ap50`` / ``ap70`` (dataset AP) and ``ap70_clean``; ``attack_success``, the share of
    honest ego-steps whose AP@0.7 fell by more than :data:`SUCCESS_DROP`;
    ``detection_rate`` / ``honest_rejected``, the shares of attacker / honest slots
    rejected; ``clean_rejected``, honest slots rejected in the clean twin (NaN where
    there is nothing to count)."""
    honest = frozenset(log.frames) - log.attackers
    ap = log.ap(honest)
    drops = [clean.ap70[key] - value > SUCCESS_DROP for key, value in log.ap70.items()
             if key[0] in honest and key in clean.ap70]
    return {"ap30": ap[0.3], "ap50": ap[0.5], "ap70": ap[0.7],
            "ap70_clean": clean.ap(honest)[0.7],
            "attack_success": float(np.mean(drops)) if drops else float("nan"),
            "detection_rate": log.rejected(honest, log.attackers, True),
            "honest_rejected": log.rejected(honest, log.attackers, False),
            "clean_rejected": clean.rejected(honest, log.attackers, False)}
