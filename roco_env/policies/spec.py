"""Policy specs: a policy and its parameters as one line of text.

Used wherever a policy is named in text: the command line, sweeps, and scenario fields that
name a policy (``action.base``, ``action.choices``).

Policy spec syntax (shell-safe, no brackets): ``NAME`` or ``NAME:KEY=VALUE,KEY=VALUE``,
e.g. ``roco``, ``roco:tau2=2``, ``roco:use_edge_similarity=false,tau2=1.5``; NAME is a
registered policy or an import target ``my_pkg.module:make_policy`` (then
``my_pkg.module:make_policy:KEY=VALUE``).
Values are YAML scalars (``2`` -> int, ``1.5`` -> float, ``false`` -> bool,
``null`` -> None, e.g. ``roco:robust_kernel=null``; anything else -> str). The canonical
form sorts the keys, so ``roco:b=1,a=2`` and ``roco:a=2,b=1`` name the same sweep cell.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import yaml

from roco_env.policies import Policy, available_policies, is_import_target, make_policy
from roco_env.scenario import ALIASES
from roco_env.schema import load_yaml

Scalar = bool | int | float | str | None


def parse_scalar(text: str, name: str) -> Scalar:
    """A YAML scalar from ``text``; ValueError naming ``name`` for lists and maps."""
    try:
        value = load_yaml(text)
    except yaml.YAMLError as exc:
        raise ValueError(f"{name}: cannot parse value {text!r}: {exc}") from exc
    if value is None or isinstance(value, bool | int | float | str):
        return value
    raise ValueError(f"{name}: value {text!r} must be a number, true/false, null or a word")


def format_scalar(value: Scalar) -> str:
    """Inverse of :func:`parse_scalar` for canonical spec strings."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        text = repr(value)  # shortest text that reads back to the same float
        if "e" in text and "." not in text:  # YAML 1.1 floats need a dot: 1e+16 -> 1.0e+16
            mantissa, exponent = text.split("e")
            text = f"{mantissa}.0e{exponent}"
        return text
    return str(value)


def parse_assignment(text: str, what: str) -> tuple[str, Scalar]:
    """``KEY=VALUE`` -> (key, scalar). ``what`` names the option in errors."""
    key, sep, value = text.partition("=")
    key = key.strip()
    if not sep or not key or not value.strip():
        raise ValueError(f"{what}: expected KEY=VALUE, got {text!r}")
    return key, parse_scalar(value.strip(), f"{what} {key}")


@dataclass(frozen=True)
class PolicySpec:
    """A registered policy name plus constructor parameters (sorted by key)."""

    name: str
    params: tuple[tuple[str, Scalar], ...] = ()

    @property
    def label(self) -> str:
        """Canonical spec text, e.g. ``roco:tau2=2``."""
        if not self.params:
            return self.name
        return self.name + ":" + ",".join(f"{k}={format_scalar(v)}" for k, v in self.params)

    def build(self) -> Policy:
        """A fresh policy instance (one per agent: policies may keep state)."""
        return make_policy(self.name, **dict(self.params))


def parse_policy_spec(text: str) -> PolicySpec:
    """Parse ``NAME[:KEY=VALUE,...]`` or ``module:factory[:KEY=VALUE,...]``; the name must be
    registered or have the import-target form (parameters unchecked)."""
    name, _, rest = text.strip().partition(":")
    name = name.strip()
    factory, sep, after = rest.partition(":")
    if name not in available_policies() and factory.strip() and "=" not in factory:
        # an import target 'my_pkg.module:make_policy'
        name, rest = f"{name}:{factory.strip()}", after
    if name not in available_policies() and not is_import_target(name):
        raise ValueError(
            f"unknown policy {name!r} in policy spec {text!r}; "
            f"available: {', '.join(available_policies())} or an import target "
            "'my_pkg.module:make_policy'"
        )
    params: dict[str, Scalar] = {}
    if rest.strip():
        for item in rest.split(","):
            key, value = parse_assignment(item, f"policy spec {text!r}")
            if key in params:
                raise ValueError(f"policy spec {text!r}: parameter {key!r} given twice")
            params[key] = value
    return PolicySpec(name, tuple(sorted(params.items())))


def validate_policy_spec(text: str) -> PolicySpec:
    """Parse and construct the policy once so bad parameters fail before a sweep starts: the
    policy's own check (the message names the spec, the key and the allowed values)."""
    spec = parse_policy_spec(text)
    try:
        spec.build()
    except (TypeError, ValueError) as exc:  # TypeError: an unknown keyword argument
        raise ValueError(f"policy spec {text!r}: {exc}") from exc
    return spec


def merge_env_overrides(overrides: Mapping[str, Any], policy: object,
                        label: str = "policy") -> dict[str, Any]:
    """``overrides`` plus the env modes ``policy`` acts in (its ``env_overrides`` mapping of
    dotted scenario fields, e.g. ``{"action.mode": "select"}``; none for a correction policy).

    A field set in both to different values is a ValueError naming the field and both values
    (aliases such as ``fusion`` are compared with their dotted name).
    """
    declared = getattr(policy, "env_overrides", None) or {}
    if not isinstance(declared, Mapping):
        raise ValueError(f"{label}: env_overrides must be a mapping of scenario fields; "
                         f"got {declared!r}")
    merged = dict(overrides)
    given = {ALIASES.get(key, key): value for key, value in overrides.items()}
    for key, value in declared.items():
        dotted = ALIASES.get(key, key)
        if dotted in given and given[dotted] != value:
            raise ValueError(f"{label} acts with {dotted}={value!r}, but the env sets "
                             f"{dotted}={given[dotted]!r}; leave {dotted} out")
        if dotted not in given:
            merged[key] = value
    return merged


ALIGNER = ("the policy spec of an aligner (e.g. 'roco', 'roco_antialias', 'roco_fallback'), "
           "not a registered policy that declares its own action.mode (e.g. defend, "
           "privileged_gate, reject_untested, learned_select, learned_fallback)")


def check_aligner_spec(where: str, field: str, text: object) -> None:
    """Raise ValueError naming ``where`` and ``field`` unless ``text`` is a policy spec the
    registry builds (a registered name or import target, with valid parameters) into a
    policy that declares no ``action.mode`` in its ``env_overrides``: an aligner the env
    can run as one of its ``action.choices`` or as ``action.base``."""
    if not isinstance(text, str) or not text.strip():
        raise ValueError(f"{where}: {field} must be {ALIGNER}; got {text!r}")
    try:
        policy = parse_policy_spec(text).build()
    except (TypeError, ValueError) as exc:  # TypeError: an unknown keyword argument
        raise ValueError(f"{where}: {field} must be {ALIGNER}; got {text!r}: {exc}") from exc
    mode = (getattr(policy, "env_overrides", None) or {}).get("action.mode")
    if mode is not None:
        raise ValueError(f"{where}: {field} must be {ALIGNER}; got {text!r}, which acts in "
                         f"action.mode {mode!r}")
