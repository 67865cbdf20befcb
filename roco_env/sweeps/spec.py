"""Text specs of the sweep and the CLI: ``KEY=VALUE`` scenario overrides, and the policy
specs of :mod:`roco_env.policies.spec` (re-exported: the sweep's cells name policies by them).
"""

from __future__ import annotations

from collections.abc import Iterable

from roco_env.policies.spec import (
    PolicySpec,
    Scalar,
    format_scalar,
    parse_assignment,
    parse_policy_spec,
    parse_scalar,
    validate_policy_spec,
)

__all__ = ["PolicySpec", "Scalar", "format_scalar", "parse_assignment", "parse_overrides",
           "parse_policy_spec", "parse_scalar", "validate_policy_spec"]


def parse_overrides(items: Iterable[str]) -> dict[str, Scalar]:
    """Scenario overrides from ``KEY=VALUE`` strings (``--set detector=ideal``)."""
    overrides: dict[str, Scalar] = {}
    for item in items:
        key, value = parse_assignment(item, "--set")
        if key in overrides:
            raise ValueError(f"--set {key} given twice ({format_scalar(overrides[key])}, then "
                             f"{format_scalar(value)})")
        overrides[key] = value
    return overrides
