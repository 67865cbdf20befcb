"""Alignment policies and their registry (algorithms and equations: docs/alignment.md).

``make_policy(name, **params)`` builds a registered policy; ``available_policies()``
lists the names. A user policy is any callable ``policy(obs, info=None) -> action``
(``make_policy`` returns it as a :class:`~roco_env.policies.base.Policy`, with the
``reset``, ``keeps_state`` and ``last_result`` it lacks given by
:func:`~roco_env.policies.base.as_policy`); three ways make it a name everywhere a policy
name is accepted (``make_policy``, ``roco-env compare --policies``, ``roco-env run
--policy``):

* ``"my_pkg.module:make_policy"``: an import target, ``module:factory``;
* ``register_policy("mine", "my_pkg.module:make_policy")`` in your own code;
* an installed package's entry point in the group :data:`ENTRY_POINT_GROUP`::

      [project.entry-points."roco_env.policies"]
      mine = "my_pkg.module:make_policy"

The factory is called with the spec's parameters and returns the callable; it checks
them itself (the built-ins through a :func:`roco_env.schema.spec` parameter dataclass),
so a bad parameter is the factory's error, naming the key and
what is allowed (``roco_env.policies.spec.validate_policy_spec`` builds a spec's policy
once to find it before a sweep starts).
"""

from __future__ import annotations

import importlib
import importlib.metadata
import sys
from collections.abc import Callable
from typing import Any

from roco_env.policies.base import (
    AlignmentResult,
    Policy,
    apply_correction,
    as_policy,
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
    "roco_antialias": "roco_env.policies.antialias:AntiAliasPolicy",
    "ransac": "roco_env.policies.ransac:RansacPolicy",
    "v2i_calib": "roco_env.policies.v2i_calib:V2ICalibPolicy",
    "freealign": "roco_env.policies.freealign:FreeAlignPolicy",
    "roco_fallback": "roco_env.policies.fallback:RoCoFallbackPolicy",
    # a base aligner on boxes brought to the ego's time (the network stage's late messages)
    "compensate": "roco_env.policies.compensate:Compensate",
    # acts in action.mode gate with observation.mode aligned (its env_overrides)
    "defend": "roco_env.policies.defend:Defend",
    # the perfect rejection (info["privileged"]): a reference for defences, in gate mode
    "privileged_gate": "roco_env.policies.privileged_gate:PrivilegedGate",
    # rejects what the aligner could not check (no statistic), in select mode
    "reject_untested": "roco_env.policies.reject_untested:RejectUntested",
    # acts in action.mode select (its env_overrides; roco_env.policies.learned)
    "learned_select": "roco_env.policies.learned:learned_select",
    # hand rule C on tested slots, a network on the untested ones (select mode)
    "learned_fallback": "roco_env.policies.learned:learned_fallback",
}


# Installed packages register policies under this entry-point group.
ENTRY_POINT_GROUP = "roco_env.policies"


# (sys.path when scanned, entry points found then): see _entry_points.
_SCANNED: tuple[tuple, dict[str, str]] | None = None


def _entry_points(refresh: bool = False) -> dict[str, str]:
    """Installed packages' policies (name -> "module:factory"). A scan reads every
    installed distribution's metadata (milliseconds), so it is kept until ``sys.path``
    changes or ``refresh`` asks for a new one (make_policy does for an unknown name: a
    package installed since the last scan)."""
    global _SCANNED
    if refresh or _SCANNED is None or _SCANNED[0] != tuple(sys.path):
        found = importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)
        _SCANNED = (tuple(sys.path), {ep.name: ep.value for ep in found})
    return _SCANNED[1]


def _registry(refresh: bool = False) -> dict[str, str]:
    """Built-in and registered policies, plus installed packages' entry points (which
    never replace a name already taken)."""
    return {**_entry_points(refresh), **_REGISTRY}


def available_policies() -> list[str]:
    """Registered names accepted by :func:`make_policy` (import targets are accepted too)."""
    return sorted(_registry())


def is_import_target(name: str) -> bool:
    """Whether ``name`` has the ``module:factory`` form of an import target."""
    module_name, sep, factory = name.partition(":")
    return bool(sep) and all(part.isidentifier() for part in module_name.split(".")) \
        and factory.isidentifier()


def register_policy(name: str, target: str) -> None:
    """Register ``"module:factory"`` under ``name`` (for extensions)."""
    module_name, _, factory = target.partition(":")
    if not module_name or not factory:
        raise ValueError(f"register_policy target must be 'module:factory'; got {target!r}")
    _REGISTRY[name] = target


def registered_policies() -> dict[str, str]:
    """The built-in and ``register_policy`` names with their ``"module:factory"`` targets
    (installed packages' entry points left out: every process finds those itself)."""
    return dict(_REGISTRY)


def make_policy(name: str, **params: Any) -> Policy:
    """Build the policy registered as ``name``, or imported from ``module:factory``; a
    factory returning a plain callable gets the :class:`Policy` members it lacks."""
    return as_policy(_factory(name)(**params), f"what {name}() returned")


def _factory(name: str) -> Callable:
    """The factory registered as ``name``, or imported from ``module:factory``."""
    if not isinstance(name, str):
        raise ValueError(f"make_policy: name must be a policy name (available_policies()) or "
                         f"an import target 'my_pkg.module:make_policy'; got {name!r} "
                         f"({type(name).__name__})")
    registry = _registry()
    if name not in registry and not is_import_target(name):
        registry = _registry(refresh=True)
    if name in registry:
        target = registry[name]
    elif is_import_target(name):
        target = name
    elif name.partition(":")[0] in registry:
        base, _, settings = name.partition(":")
        raise ValueError(f"unknown policy {name!r}: make_policy takes parameters as keyword "
                         f"arguments, make_policy({base!r}, ...) for {settings!r}; the "
                         "'NAME:KEY=VALUE' spec is the command line's "
                         "(roco_env.policies.spec.parse_policy_spec reads it)")
    else:
        raise ValueError(f"unknown policy {name!r}; available: {', '.join(sorted(registry))} "
                         "or an import target 'my_pkg.module:make_policy'")
    module_name, factory = target.split(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ValueError(f"policy {name!r}: cannot import module {module_name!r}: {exc}") from exc
    if not callable(getattr(module, factory, None)):
        raise ValueError(f"policy {name!r}: module {module_name!r} has no callable {factory!r}")
    return getattr(module, factory)


__all__ = [
    "AlignmentResult",
    "Policy",
    "apply_correction",
    "ENTRY_POINT_GROUP",
    "available_policies",
    "correction_action",
    "is_import_target",
    "make_policy",
    "register_policy",
    "registered_policies",
    "reported_relative_poses",
]
