"""Play a cell with per-agent act functions that may read the env's own select-mode
alignments (``env._choices``): the baselines' scripts that compare them with the truth."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import roco_env.sweeps.episode as episode
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
