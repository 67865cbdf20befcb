"""The sweep grid: scenario x density x grid axes x noise level x policy x seed, one
episode per cell.

A :class:`Cell` is plain data (picklable, JSON-able) with a stable text ``key``
used for resuming: the same settings always give the same key.
Noise level ``s`` means sigma_t = s m and sigma_r = s deg (the paper's "s/s"). A grid
axis (``roco-env compare --grid KEY=V1,V2``) makes any other scenario field an axis: each
cell carries its value among its overrides (so its key, and resuming, see it).
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any

from roco_env.env import check_seed
from roco_env.scenario import load_scenario
from roco_env.sweeps.text_specs import (
    Scalar,
    format_scalar,
    parse_policy_spec,
    validate_policy_spec,
)

# Overrides the grid sets itself; a grid-level override may not fight them.
GRID_OWNED_OVERRIDES = ("sigma_t", "sigma_r", "density", "noise.sigma_t", "noise.sigma_r",
                        "traffic.density")


@dataclass(frozen=True)
class Cell:
    """One episode of the sweep.

    scenario: scenario name or YAML path; noise: level s (sigma_t = s m, sigma_r = s deg),
    None = the scenario's own sigma_t / sigma_r (``roco-env stress`` cells); policy: canonical policy spec (see :mod:`roco_env.sweeps.text_specs`); seed: env reset seed;
    steps: env steps (max_cycles); density: traffic density override, None = scenario
    default; overrides: further scenario overrides as sorted (key, value) pairs.
    """

    scenario: str
    noise: float | None
    policy: str
    seed: int
    steps: int
    density: float | None = None
    overrides: tuple[tuple[str, Scalar], ...] = ()

    @property
    def key(self) -> str:
        """Stable identity of the cell, e.g. ``urban|density=default|noise=0.4|policy=roco|...``."""
        density = "default" if self.density is None else format_scalar(float(self.density))
        noise = "default" if self.noise is None else format_scalar(float(self.noise))
        parts = [
            self.scenario,
            f"density={density}",
            f"noise={noise}",
            f"policy={self.policy}",
            f"seed={self.seed}",
            f"steps={self.steps}",
        ]
        parts += [f"{k}={format_scalar(v)}" for k, v in self.overrides]
        return "|".join(parts)

    def env_overrides(self) -> dict[str, Any]:
        """Keyword overrides for ``roco_env.parallel_env``."""
        kwargs: dict[str, Any] = dict(self.overrides)
        if self.noise is not None:
            kwargs["sigma_t"] = float(self.noise)
            kwargs["sigma_r"] = float(self.noise)
        if self.density is not None:
            kwargs["density"] = float(self.density)
        return kwargs

    def to_dict(self) -> dict[str, Any]:
        data = asdict(self)
        data["overrides"] = dict(self.overrides)
        return data

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Cell:
        fields = dict(data)
        fields["overrides"] = tuple(sorted(dict(fields.get("overrides", {})).items()))
        return cls(**fields)


def build_grid(
    scenarios: Sequence[str],
    noises: Sequence[float],
    policies: Sequence[str],
    seeds: Sequence[int],
    steps: int,
    densities: Sequence[float | None] = (None,),
    overrides: Mapping[str, Scalar] | None = None,
    axes: Mapping[str, Sequence[Scalar]] | None = None,
) -> list[Cell]:
    """All cells of the grid in a stable order (scenario, density, axes, noise, policy,
    seed). ``axes``: scenario field -> its values, one more dimension each.

    Checks shapes and ranges that need no env (non-empty lists, steps >= 1, noise >= 0,
    density >= 0, seeds >= 0, registered policy names); see :func:`validate_grid` for the
    full check.
    """
    axes = dict(axes or {})
    for name, values in (("scenarios", scenarios), ("noises", noises), ("policies", policies),
                         ("seeds", seeds), ("densities", densities),
                         *((f"grid axis {key}", values) for key, values in axes.items())):
        if len(values) == 0:
            raise ValueError(f"{name} must not be empty")
    if int(steps) != steps or steps < 1:
        raise ValueError(f"steps must be an integer >= 1; got {steps}")
    for noise in noises:
        if not noise >= 0:
            raise ValueError(f"noise levels must be >= 0 (sigma_t m / sigma_r deg); got {noise}")
    for density in densities:
        if density is not None and not density >= 0:
            raise ValueError(f"densities must be >= 0; got {density}")
    for seed in seeds:
        check_seed(seed)
    extra = dict(overrides or {})
    clash = sorted((set(extra) | set(axes)) & set(GRID_OWNED_OVERRIDES))
    if clash:
        raise ValueError(
            f"override {clash[0]!r} is set by the grid; use the noise/density lists instead "
            "(roco-env: --noise / --density)"
        )
    both = sorted(set(extra) & set(axes))
    if both:
        raise ValueError(f"{both[0]!r} is both an override and a grid axis; give it once "
                         "(roco-env: --set or --grid)")
    labels = [parse_policy_spec(p).label for p in policies]
    settings = [tuple(sorted({**extra, **dict(zip(axes, values, strict=True))}.items()))
                for values in itertools.product(*axes.values())]
    cells = [
        Cell(scenario=s, noise=float(n), policy=p, seed=int(seed), steps=int(steps),
             density=None if d is None else float(d), overrides=items)
        for s, d, items, n, p, seed in itertools.product(scenarios, densities, settings, noises,
                                                         labels, seeds)
    ]
    unique = {c.key: c for c in cells}
    return list(unique.values())


def validate_grid(cells: Sequence[Cell]) -> None:
    """Fail fast (ValueError naming the bad value) on anything a cell would raise on.

    Loads each distinct scenario with its overrides (unknown scenario, bad override or
    out-of-range noise/density) and builds each distinct policy spec once.
    """
    for scenario, overrides in sorted({(c.scenario, tuple(sorted(c.env_overrides().items())))
                                       for c in cells}):
        load_scenario(scenario, **dict(overrides))
    for policy in sorted({c.policy for c in cells}):
        validate_policy_spec(policy)
