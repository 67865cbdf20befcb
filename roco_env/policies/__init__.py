"""Alignment policies and their registry (DESIGN.md section 6).

``make_policy(name, **params)`` builds a built-in policy; ``available_policies()``
lists the names. A user policy is any callable ``policy(obs, info=None) -> action``.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

from roco_env.policies.base import (
    AlignmentResult,
    apply_correction,
    correction_action,
    reported_relative_poses,
)

# name -> "module:factory"; imported lazily so `import roco_env` stays light.
_REGISTRY: dict[str, str] = {
    "identity": "roco_env.policies.basic:IdentityPolicy",
    "oracle": "roco_env.policies.basic:OraclePolicy",
    "coalign": "roco_env.policies.coalign:CoAlignPolicy",
    "roco": "roco_env.policies.roco:RoCoPolicy",
    "coalign_temporal": "roco_env.policies.temporal:coalign_temporal",
    "roco_temporal": "roco_env.policies.temporal:roco_temporal",
    "ransac": "roco_env.policies.ransac:RansacPolicy",
    "v2i_calib": "roco_env.policies.v2i_calib:V2ICalibPolicy",
    "freealign": "roco_env.policies.freealign:FreeAlignPolicy",
    "roco_fallback": "roco_env.policies.fallback:RoCoFallbackPolicy",
}


def available_policies() -> list[str]:
    """Names accepted by :func:`make_policy`."""
    return sorted(_REGISTRY)


def register_policy(name: str, target: str) -> None:
    """Register ``"module:factory"`` under ``name`` (for extensions)."""
    module_name, _, factory = target.partition(":")
    if not module_name or not factory:
        raise ValueError(f"register_policy target must be 'module:factory'; got {target!r}")
    _REGISTRY[name] = target


def make_policy(name: str, **params: Any) -> Callable:
    """Build the policy registered as ``name`` with its parameters."""
    if name not in _REGISTRY:
        raise ValueError(f"unknown policy {name!r}; available: {', '.join(available_policies())}")
    module_name, factory = _REGISTRY[name].split(":")
    return getattr(importlib.import_module(module_name), factory)(**params)


__all__ = [
    "AlignmentResult",
    "apply_correction",
    "available_policies",
    "correction_action",
    "make_policy",
    "register_policy",
    "reported_relative_poses",
]
