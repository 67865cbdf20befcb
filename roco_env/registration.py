"""The environment's registry ids and their registration.

:data:`ENV_ID` names the PettingZoo env (parallel and AEC) and is its
``metadata["name"]``; :data:`EGO_ENV_ID` names the single-agent Gymnasium view.
``import roco_env`` calls :func:`register`; the entry points are named by text, so
registering imports none of the environment.
"""

from __future__ import annotations

import gymnasium
import pettingzoo

ENV_ID = "roco/CollabPerception-v0"
EGO_ENV_ID = "roco/CollabPerceptionEgo-v0"


def register() -> None:
    """Enter :data:`ENV_ID` in PettingZoo's parallel and AEC registries and
    :data:`EGO_ENV_ID` in Gymnasium's (once: a second call changes nothing). The
    entry points' own defaults apply (``max_cycles`` is the env's)."""
    if ENV_ID not in pettingzoo.parallel_registry:
        pettingzoo.register("parallel", ENV_ID, entry_point="roco_env.env:parallel_env")
        pettingzoo.register("aec", ENV_ID, entry_point="roco_env.env:aec_env")
    if EGO_ENV_ID not in gymnasium.registry:
        gymnasium.register(EGO_ENV_ID, entry_point="roco_env.wrappers:EgoEnv")
