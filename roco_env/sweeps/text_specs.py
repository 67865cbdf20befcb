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

__all__ = ["PolicySpec", "Scalar", "format_scalar", "parse_assignment", "parse_grid",
           "parse_overrides", "parse_policy_spec", "parse_scalar", "validate_policy_spec"]


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


def parse_grid(items: Iterable[str]) -> dict[str, tuple[Scalar, ...]]:
    """Grid axes from ``KEY=V1,V2,...`` strings (``--grid comm.delay_params.delay_ms=0,100``):
    each a scenario field and its values (YAML scalars), in the order given."""
    axes: dict[str, tuple[Scalar, ...]] = {}
    for item in items:
        key, sep, text = item.partition("=")
        key = key.strip()
        words = [word.strip() for word in text.split(",")]
        if not sep or not key or not all(words):
            raise ValueError(f"--grid: expected KEY=V1,V2,... (values separated by commas, "
                             f"none empty), got {item!r}")
        if key in axes:
            raise ValueError(f"--grid {key} given twice; give its values in one --grid")
        values = tuple(parse_scalar(word, f"--grid {key}") for word in words)
        repeated = sorted({format_scalar(v) for v in values if values.count(v) > 1})
        if repeated:
            raise ValueError(f"--grid {key}: value {repeated[0]} given twice")
        axes[key] = values
    return axes
