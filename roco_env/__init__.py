"""roco-env: pose-robust collaborative 3D perception as a PettingZoo environment.

    import roco_env
    env = roco_env.parallel_env("urban_intersection", max_cycles=100, sigma_t=0.4)
    aec = roco_env.env("urban_intersection")          # AEC version
    roco_env.list_scenarios()

As in PettingZoo's environment modules, ``roco_env.parallel_env(...)`` builds the
ParallelEnv (:class:`CollabPerceptionEnv`, whose docstring is the contract) and
``roco_env.env(...)`` the AEC env; both take the same arguments. ``roco_env.env`` is
also the environment's module (``from roco_env.env import CollabPerceptionEnv``,
``import roco_env.env as m``): the module is callable, and calling it is calling its
:func:`~roco_env.env.aec_env`.

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
from typing import Any

from roco_env import registration
from roco_env.registration import EGO_ENV_ID, ENV_ID
from roco_env.scenario import (
    ScenarioConfig,
    list_scenarios,
    load_scenario,
    save_scenario,
    scenario_from_dict,
    scenario_to_dict,
)
from roco_env.stages import available_stages, register_stage

__version__ = '0.1.0'

__all__ = ["EGO_ENV_ID", "ENV_ID", "CollabPerceptionEnv", "ScenarioConfig", "__version__",
           "available_stages", "env", "list_scenarios", "load_scenario", "parallel_env",
           "register_stage", "save_scenario", "scenario_from_dict", "scenario_to_dict"]

# Package attributes defined in roco_env/env.py, imported on first access so that
# ``import roco_env`` stays light. ``env`` is the (callable) module itself.
_FROM_ENV_MODULE = ("parallel_env", "CollabPerceptionEnv")


def __getattr__(name: str) -> Any:
    if name == "env":
        return importlib.import_module("roco_env.env")
    if name in _FROM_ENV_MODULE:
        return getattr(importlib.import_module("roco_env.env"), name)
    raise AttributeError(f"module 'roco_env' has no attribute {name!r}")


registration.register()
