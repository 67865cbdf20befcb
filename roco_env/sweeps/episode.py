"""Run one sweep cell: one env episode with one policy instance per agent, scored.

The episode is :func:`roco_env.rollout.play_episode` (the env checks every action);
this module scores what it yields.

Scores (docs/metrics.md), pooled over every evaluated agent and step:
* dataset AP@0.3/0.5/0.7 from the infos' exact per-frame data
  (``frame_scores``, ``frame_tp``, ``frame_fp``, ``frame_n_gt``);
* relative pose error of every filled collaborator slot before and after the
  correction (translation m, rotation deg): median, 95th percentile,
  Success@1m1deg, @2m2deg and @3m3deg; the samples are kept for distribution plots;
* matching precision/recall against true object ids, mean over the frames where
  the policy reported a match result of that call (``policy.last_result``), using the privileged
  ids of the info returned *with* the observation the policy saw;
* correction share: frames (agent-steps with >= 1 collaborator) where the action
  changed a filled slot's reported pose;
* with the network stage on (docs/network.md): the bytes an agent receives per step,
  mean over agent-steps;
* time per call: median wall time (ms) of one *warm* policy call, stored beside the
  metrics (a wall time, not reproducible): each agent's first call is left out, as it
  includes one-off costs (numba compiling the kernels in a fresh worker, the policy's
  first-use set-up: many warm calls' worth, docs/performance.md); the median keeps a
  later one-off (a kernel first needed at step k) from weighing in.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

import roco_env
from roco_env.evaluation import filled_rpe_rows, info_frame_stats
from roco_env.metrics import DEFAULT_IOU_THRESHOLDS, APAccumulator, matching_precision_recall
from roco_env.policies.base import AlignmentResult
from roco_env.policies.spec import merge_env_overrides
from roco_env.rollout import play_episode
from roco_env.sweeps.cells import Cell
from roco_env.sweeps.records import error_record, ok_record
from roco_env.sweeps.stats import nanmean, pose_error_summary
from roco_env.sweeps.text_specs import parse_policy_spec

SAMPLE_DECIMALS = 3  # RPE samples are stored to 1 mm / 0.001 deg (plots, pooled percentiles)
_ACTION_EPS = 1e-9  # |correction| below this counts as "kept the reported pose"

PolicyFactory = Callable[[], Callable]
StepCallback = Callable[[int, Any, dict, dict], None]


@dataclass
class EpisodeScorer:
    """Accumulates one episode's decisions (policy side) and outcomes (env side)."""

    ap: APAccumulator = field(default_factory=lambda: APAccumulator(DEFAULT_IOU_THRESHOLDS))
    before: list = field(default_factory=list)
    after: list = field(default_factory=list)
    precision: list = field(default_factory=list)
    recall: list = field(default_factory=list)
    applied: list = field(default_factory=list)
    received: list = field(default_factory=list)  # bytes per agent-step (network on)
    call_seconds: dict[str, list[float]] = field(default_factory=dict)  # by agent, in order
    decisions: int = 0  # agent-steps with >= 1 collaborator
    steps: int = 0  # env steps played (fewer than asked when a replay's frames run out)

    def add_decision(self, observation: dict, info: dict, action: Any,
                     result: AlignmentResult | None) -> None:
        """Score an action taken on ``observation`` (``info`` came with it); ``result`` is
        the policy's alignment result for this very call, None when it reported none;
        ``action`` is the (N, 3) correction the env accepted, None in the other action
        modes (whose actions are no corrections: the correction share is left undefined)."""
        filled = np.asarray(observation["collab_mask"]) > 0
        if not filled.any():
            return
        self.decisions += 1
        if action is not None:
            moved = np.abs(np.asarray(action, dtype=float)[filled]) > _ACTION_EPS
            self.applied.append(bool(moved.any()))
        privileged = info.get("privileged") if info else None
        if result is None or privileged is None:
            return
        precision, recall = matching_precision_recall(
            result, privileged["box_object_ids"], privileged["collab_box_object_ids"],
            ego_mask=observation["box_mask"], collab_mask=observation["collab_box_mask"])
        self.precision.append(precision)
        self.recall.append(recall)

    def add_outcome(self, info: dict) -> None:
        """Pool an agent's post-step info (its fused frame and RPE rows)."""
        if "frame_scores" in info:
            self.ap.add_stats(info_frame_stats(info))
        if "rpe_before" in info:
            self.before.append(filled_rpe_rows(info["rpe_before"]))
            self.after.append(filled_rpe_rows(info["rpe_after"]))
        if "bytes_received" in info:
            self.received.append(info["bytes_received"])

    def add_call(self, agent: str, seconds: float) -> None:
        """Record the wall time (s) of one call of ``agent``'s policy."""
        self.call_seconds.setdefault(agent, []).append(seconds)

    def time_per_call_ms(self) -> float:
        """Median wall time (ms) of one warm policy call: every agent's calls after its
        first (which pays the one-off compilation and set-up); NaN without any."""
        warm = [seconds for calls in self.call_seconds.values() for seconds in calls[1:]]
        return 1e3 * float(np.median(warm)) if warm else float("nan")

    def summary(self) -> tuple[dict[str, float], dict[str, list]]:
        """(metrics, samples): scalar metrics and rounded RPE samples [[t m, r deg], ...]."""
        ap = self.ap.ap()
        before = np.concatenate(self.before) if self.before else np.zeros((0, 2))
        after = np.concatenate(self.after) if self.after else np.zeros((0, 2))
        metrics = {"ap30": ap[0.3], "ap50": ap[0.5], "ap70": ap[0.7]}
        metrics.update(pose_error_summary(before, after))
        metrics["match_precision"] = nanmean(self.precision)
        metrics["match_recall"] = nanmean(self.recall)
        metrics["correction_share"] = nanmean(self.applied)
        if self.received:
            metrics["bytes_received"] = nanmean(self.received)
        metrics["frames"] = self.ap.n_frames  # evaluated agent-steps
        metrics["decisions"] = self.decisions  # agent-steps with >= 1 collaborator
        metrics["matched_frames"] = len(self.precision)  # decisions with an alignment result
        metrics["pairs"] = int(after.shape[0])
        metrics["steps"] = self.steps
        samples = {
            "before": np.round(before, SAMPLE_DECIMALS).tolist(),
            "after": np.round(after, SAMPLE_DECIMALS).tolist(),
        }
        return metrics, samples


def make_env(cell: Cell, render_mode: str | None = None, policy: object | None = None):
    """The cell's PettingZoo ParallelEnv (scenario + noise/density/other overrides), in the
    env modes ``policy`` declares (its ``env_overrides``, e.g. a learned select-mode policy's
    ``action.mode``; a conflict with the cell's overrides is a ValueError naming the field)."""
    overrides = merge_env_overrides(cell.env_overrides(), policy, f"policy {cell.policy!r}")
    return roco_env.parallel_env(cell.scenario, max_cycles=cell.steps, render_mode=render_mode,
                                 **overrides)


def run_episode(cell: Cell, policy_factory: PolicyFactory | None = None,
                on_step: StepCallback | None = None,
                render_mode: str | None = None,
                on_scorer: Callable[[EpisodeScorer], None] | None = None,
                ) -> tuple[dict[str, float], dict[str, list]]:
    """Run ``cell`` and return (metrics, samples) as in :meth:`EpisodeScorer.summary`.

    ``policy_factory`` builds one policy per agent (default: the cell's policy spec);
    ``on_step(step, env, actions, infos)`` is called after every env step (step from 1),
    e.g. to print per-step metrics or ``env.render()`` a frame; ``on_scorer(scorer)``
    receives the episode's :class:`EpisodeScorer` (its wall times stay out of the metrics).
    """
    factory = policy_factory or parse_policy_spec(cell.policy).build
    first = factory()  # its env_overrides say which env modes it acts in
    env = make_env(cell, render_mode, first)
    try:
        policies = {agent: first if index == 0 else factory()
                    for index, agent in enumerate(env.possible_agents)}
        correction = env.config.action.mode == "correction"
        scorer = EpisodeScorer()
        if on_scorer is not None:
            on_scorer(scorer)
        for step in play_episode(env, policies, seed=cell.seed, max_steps=cell.steps):
            for agent, turn in step.turns.items():  # the env accepted every action
                scorer.add_call(agent, turn.seconds)
                scorer.add_decision(turn.observation, turn.info,
                                    turn.action if correction else None, turn.result)
            scorer.steps = step.number
            for info in step.infos.values():
                scorer.add_outcome(info)
            if on_step is not None:
                on_step(step.number, env, step.actions, step.infos)
        return scorer.summary()
    finally:
        env.close()


def run_cell(cell: Cell) -> dict[str, Any]:
    """The stored record of one cell; an exception becomes an ``error`` record (never raised).

    Module-level and argument-only so process pools and Ray can ship it.
    """
    start = time.perf_counter()
    scorers: list[EpisodeScorer] = []
    try:
        metrics, samples = run_episode(cell, on_scorer=scorers.append)
    except Exception as exc:  # noqa: BLE001 - a failing cell is recorded, the sweep goes on
        return error_record(cell, exc, time.perf_counter() - start)
    return ok_record(cell, metrics, samples, time.perf_counter() - start,
                     scorers[0].time_per_call_ms())
