"""roco-env: pose-robust collaborative 3D perception as a PettingZoo environment.

    import roco_env
    env = roco_env.parallel_env("urban_intersection", max_cycles=100, sigma_t=0.4)
    aec = roco_env.env("urban_intersection")          # AEC version
    roco_env.list_scenarios()

Scenarios: :func:`load_scenario` (name or YAML path), :func:`scenario_from_dict` /
:func:`scenario_to_dict` (plain mappings with the YAML keys, validated) and
:func:`save_scenario` (a config to a YAML file that loads back equal).

Importing the package is cheap (the environment loads on first use; torch only
when BEV features are on) and registers ``roco/CollabPerception-v0`` in PettingZoo's registry
(``pettingzoo.make("parallel" | "aec", "roco/CollabPerception-v0", **overrides)``)
and the single-agent view ``roco/CollabPerceptionEgo-v0`` in Gymnasium's.
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import gymnasium
import pettingzoo

from roco_env.scenario import (
    ScenarioConfig,
    list_scenarios,
    load_scenario,
    save_scenario,
    scenario_from_dict,
    scenario_to_dict,
)
from roco_env.stages import available_stages, register_stage

if TYPE_CHECKING:
    from roco_env.env import CollabPerceptionEnv

__version__ = '0.1.0'

ENV_ID = "roco/CollabPerception-v0"
EGO_ENV_ID = "roco/CollabPerceptionEgo-v0"
DEFAULT_MAX_CYCLES = 100

__all__ = ["EGO_ENV_ID", "ENV_ID", "ScenarioConfig", "__version__", "available_stages", "env",
           "list_scenarios", "load_scenario", "parallel_env", "register_stage", "save_scenario",
           "scenario_from_dict", "scenario_to_dict"]


def parallel_env(scenario: str | os.PathLike | Mapping[str, Any] | ScenarioConfig
                 = "urban_intersection", max_cycles: int = DEFAULT_MAX_CYCLES,
                 render_mode: str | None = None, **overrides: Any) -> CollabPerceptionEnv:
    """The PettingZoo ParallelEnv (:class:`roco_env.env.CollabPerceptionEnv`).

    scenario: a name from :func:`list_scenarios`, a path to a YAML file, a plain
    mapping with the YAML keys (checked by :func:`roco_env.scenario.scenario_from_dict`)
    or a :class:`~roco_env.scenario.ScenarioConfig`; overrides: validated scenario
    fields (``sigma_t=0.4``, ``**{"traffic.min_gap": 1.0}``). Building the env
    imports the simulation stack; ``import roco_env`` alone stays light.
    """
    from roco_env.env import parallel_env as make

    return make(scenario, max_cycles=max_cycles, render_mode=render_mode, **overrides)


def __getattr__(name: str) -> Any:
    # ``roco_env.env`` is the module roco_env/env.py, made callable there: calling it
    # builds the AEC env. Loaded on first access to keep ``import roco_env`` light.
    if name == "env":
        return importlib.import_module("roco_env.env")
    raise AttributeError(f"module 'roco_env' has no attribute {name!r}")


if ENV_ID not in pettingzoo.parallel_registry:
    pettingzoo.register("parallel", ENV_ID, entry_point="roco_env.env:parallel_env",
                        max_cycles=DEFAULT_MAX_CYCLES)
    pettingzoo.register("aec", ENV_ID, entry_point="roco_env.env:aec_env",
                        max_cycles=DEFAULT_MAX_CYCLES)
if EGO_ENV_ID not in gymnasium.registry:
    gymnasium.register(EGO_ENV_ID, entry_point="roco_env.wrappers:EgoEnv")
