"""Play a cell with per-agent act functions that may read the env's own select-mode
alignments (``env._choices``): the baselines' scripts that compare them with the truth."""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from dataclasses import replace

import numpy as np
from privileged_bound import pose_errors

import roco_env.sweeps.episode as episode
from roco_env.evaluation import EgoEvaluation, evaluate_egos
from roco_env.fusion import suppress
from roco_env.sweeps.cells import Cell


def run_with_env(cell: Cell, label: str, make_act: Callable) -> dict[str, float]:
    """The metrics of ``cell`` (policy ``label``) played by ``make_act(index, env_of)``,
    one act function per agent (index in ``env.possible_agents``' order; it needs an
    ``env_overrides`` attribute); ``env_of()`` returns the episode's env when called."""
    envs: list = []
    make_env = episode.make_env

    def keep_env(*given, **named):
        envs.append(make_env(*given, **named))
        return envs[-1]

    agents = iter(range(1000))
    try:
        episode.make_env = keep_env
        metrics, _ = episode.run_episode(replace(cell, policy=label),
                                         lambda: make_act(next(agents), lambda: envs[-1]))
    finally:
        episode.make_env = make_env
    return metrics


def record_cell(sink, cell: Cell, label: str, metrics: dict[str, float]) -> None:
    """Append ``cell``'s AP@0.7 under policy ``label`` to ``sink`` as one line of the
    ``roco-env compare`` results.jsonl layout (``table.py`` reads it) and log it."""
    sink.write(json.dumps({"cell": {"scenario": cell.scenario, "noise": cell.noise,
                                    "policy": label, "seed": cell.seed, "overrides": {}},
                           "metrics": {"ap70": metrics["ap70"]}}) + "\n")
    sink.flush()
    print(label, cell.scenario, cell.noise, cell.seed, round(metrics["ap70"], 4),
          file=sys.stderr)


def print_counts(header: str, counts: dict) -> None:
    """A Markdown table: ``header`` (its column names after scenario and noise), then one
    row per (scenario, noise) key of ``counts`` with its values."""
    columns = header.split(" | ")
    print("| scenario | noise | " + header + " |\n|---|---|" + "---|" * len(columns))
    for (scenario, noise), row in sorted(counts.items()):
        print(f"| {scenario} | {noise} | " + " | ".join(str(value) for value in row) + " |")


def choice_errors(alignments, observation: dict, info: dict) -> tuple[int, np.ndarray]:
    """(n, (C, n) errors): the filled slot count n of ``observation`` and each select-mode
    choice's pose error on them (``alignments``: the env's ``_choices`` of the agent; the
    error of :func:`privileged_bound.pose_errors`, m / deg, against the privileged truth)."""
    n = int(np.sum(observation["collab_mask"]))
    truth = info["privileged"]["true_relative_poses"][:n]
    return n, np.stack([pose_errors(np.asarray(a.corrected)[:n], truth) for a in alignments])


def select_decisions(reported: np.ndarray, poses: np.ndarray,
                     picks: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """[(corrected (n, 3), kept (n,) bool)] of each row of ``picks`` (K, n) select actions
    (reject = C) as the env's select mode decides them: ``poses`` (C, n, 3) the choices'
    T_{j->i} (x m, y m, yaw rad), ``reported`` (n, 3) the pose a rejected slot keeps."""
    decisions = []
    for pick in np.atleast_2d(picks):
        corrected = np.asarray(reported, dtype=float).copy()
        for index, choice in enumerate(poses):
            corrected[pick == index] = choice[pick == index]
        decisions.append((corrected, pick != len(poses)))
    return decisions


def frame_evaluations(env, index: int, decisions: list[tuple[np.ndarray, np.ndarray]]
                      ) -> list[EgoEvaluation]:
    """What agent ``index`` (of ``env.possible_agents``) would score on the env's current
    frame (the one its last observation shows) with each (corrected, kept) decision of
    its filled slots, fused and scored as ``env.step`` does (one batched call; the env is
    not advanced)."""
    frame, config = env._frame, env.config
    egos = [index] * len(decisions)
    sets = env.fusion.fuse(frame, egos, [kept for _, kept in decisions],
                           [corrected[kept] for corrected, kept in decisions])
    own_car_is_truth = config.evaluation.ground_truth == "opencood"
    footprint = None if own_car_is_truth else frame.footprints[index]
    fused = suppress(sets, config.fusion.nms_iou, [footprint] * len(decisions))
    return evaluate_egos([frame.views[index]] * len(decisions), fused,
                         [corrected for corrected, _ in decisions], frame.state,
                         frame.visibility.visible, config.evaluation.x_range,
                         config.evaluation.y_range, config.max_collaborators,
                         config.evaluation.ground_truth, config.evaluation.z_range)
