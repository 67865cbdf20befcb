"""The search space of ``roco-env stress``: which scenario fields vary, and how far.

A space file (YAML) names a base scenario, the reference overrides that make the
default scene the found ones are compared against, and the parameters::

    base: urban_intersection            # every evaluation starts from this scenario
    reference: {noise.sigma_t: 1.0, noise.sigma_r: 1.0}   # the default scene's overrides
    parameters:
      traffic.layout: {type: categorical, choices: [intersection, parking_lot]}
      fill: {type: float, low: 0.2, high: 1.0}
      traffic.min_gap: {type: float, low: 0.3, high: 4.0}
      agents.cavs: {type: int, low: 2, high: 6}
      noise.sigma_t: {type: float, low: 0.1, high: 3.0, log: true}

A parameter is a dotted scenario field (``traffic.*``, ``agents.*``, ``noise.*``, ...,
scalar fields only) or the derived ``fill``: the share (0, 1] of the traffic's capacity,
which becomes ``traffic.density`` as the stall fill ratio on ``parking_lot`` and as
``fill * 100 / (CAR_LENGTH + min_gap)`` vehicles per 100 m of lane elsewhere, so one
range means "empty to packed" on every layout. Each parameter is ``float`` (``low``,
``high``, optional ``log``), ``int`` (``low``, ``high``) or ``categorical``
(``choices``). Every bound and choice is checked against the scenario field's own
allowed values; errors name the file and ``parameters.<name>.<key>``.
"""

from __future__ import annotations

import dataclasses
import importlib.resources
import os
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from roco_env.scenario import ScenarioConfig, apply_overrides, load_scenario
from roco_env.schema import ConfigError, build, check_value, load_yaml, spec

DEFAULT_SPACE = "default_space.yaml"  # package data of roco_env.stress
FILL = "fill"  # the derived parameter (see the module docstring)
CAR_LENGTH = 4.6  # m, a typical passenger car: the lane capacity is 100 / (CAR_LENGTH + gap)
PARAM_TYPES = ("float", "int", "categorical")


@dataclass
class ParamSpec:
    """One parameter's range as the space file gives it."""

    type: str = spec("float", choices=PARAM_TYPES)
    low: float | None = spec(None, doc="lowest value (float, int)")
    high: float | None = spec(None, doc="highest value (float, int)")
    log: bool = spec(False, doc="sample on a log scale (float, int; low > 0)")
    choices: list | None = spec(None, doc="the values of a categorical parameter")


@dataclass
class SpaceFile:
    """The top level of a space file."""

    base: str = spec("urban_intersection", doc="scenario name or YAML path evaluations start from")
    reference: dict = spec({}, doc="overrides of the base that make the default (reference) scene")
    parameters: dict = spec({}, doc="parameter name -> range")


@dataclass(frozen=True)
class Param:
    """A checked parameter: ``name`` (dotted scenario field or ``fill``) and its range."""

    name: str
    type: str
    low: float | None = None
    high: float | None = None
    log: bool = False
    choices: tuple = ()


@dataclass(frozen=True)
class SearchSpace:
    """A checked space: the base scenario, the reference overrides and the parameters."""

    base: str
    reference: tuple[tuple[str, Any], ...]
    params: tuple[Param, ...]
    where: str = "<space>"

    @property
    def names(self) -> list[str]:
        return [p.name for p in self.params]


def _field(dotted: str) -> tuple[Any, dict] | None:
    """(type hint, schema metadata) of a scalar scenario field ``a.b``; None when unknown."""
    cls: Any = ScenarioConfig
    parts = dotted.split(".")
    for depth, part in enumerate(parts):
        fields = {f.name: f for f in dataclasses.fields(cls)}
        if part not in fields:
            return None
        hint = typing.get_type_hints(cls)[part]
        if dataclasses.is_dataclass(hint):
            cls = hint
            continue
        scalar = next(t for t in typing.get_args(hint) or (hint,) if t is not type(None))
        if depth != len(parts) - 1 or (typing.get_origin(scalar) or scalar) in (list, dict):
            return None
        return hint, dict(fields[part].metadata)
    return None


def _scalar_fields(cls: Any = ScenarioConfig, prefix: str = "") -> list[str]:
    names = []
    for f in dataclasses.fields(cls):
        hint = typing.get_type_hints(cls)[f.name]
        if dataclasses.is_dataclass(hint):
            names += _scalar_fields(hint, f"{prefix}{f.name}.")
        elif _field(prefix + f.name) is not None:
            names.append(prefix + f.name)
    return names


def _check_param(name: str, raw: Any, where: str) -> Param:
    key = f"parameters.{name}"
    given = build(ParamSpec, raw, where, prefix=f"{key}.")
    if name == FILL:
        hint, meta = float, {"low": 0.0, "high": 1.0, "low_open": True}
    else:
        found = _field(name)
        if found is None or name in ("name", "description"):
            allowed = [FILL] + [n for n in _scalar_fields() if n not in ("name", "description")]
            raise ConfigError(f"{where}: unknown parameter {name!r}; allowed: {', '.join(allowed)}")
        hint, meta = found
    if given.type == "categorical":
        if given.low is not None or given.high is not None or given.log:
            raise ConfigError(f"{where}: {key} is categorical: give choices, not low/high/log")
        if not given.choices:
            raise ConfigError(f"{where}: {key}.choices must be a non-empty list")
        choices = tuple(check_value(c, hint, meta, where, f"{key}.choices")
                        for c in given.choices)
        if len(set(choices)) != len(choices):
            raise ConfigError(f"{where}: {key}.choices lists a value twice: {list(choices)}")
        return Param(name, "categorical", choices=choices)
    if given.choices is not None:
        raise ConfigError(f"{where}: {key} is {given.type}: give low/high, not choices")
    base = next(t for t in typing.get_args(hint) or (hint,) if t is not type(None))
    if given.type == "float" and base is not float or given.type == "int" and base is not int:
        raise ConfigError(f"{where}: {key}: type {given.type!r} does not fit the field, which "
                          f"expects {'an integer' if base is int else base.__name__}")
    for end in ("low", "high"):
        value = getattr(given, end)
        if value is None:
            raise ConfigError(f"{where}: {key}.{end} is required for a {given.type} parameter")
        if given.type == "int" and value != int(value):
            raise ConfigError(f"{where}: {key}.{end} must be an integer; got {value!r}")
        check_value(int(value) if given.type == "int" else value, base, meta, where,
                    f"{key}.{end}")
    if not given.low < given.high:
        raise ConfigError(f"{where}: {key}: low must be < high; got low={given.low}, "
                          f"high={given.high}")
    if given.log and not given.low > 0:
        raise ConfigError(f"{where}: {key}: a log range needs low > 0; got low={given.low}")
    cast = int if given.type == "int" else float
    return Param(name, given.type, cast(given.low), cast(given.high), given.log)


def parse_space(data: Any, where: str = "<space>") -> SearchSpace:
    """A :class:`SearchSpace` from a mapping; :class:`ConfigError` naming the parameter."""
    top = build(SpaceFile, data, where)
    if not top.parameters:
        raise ConfigError(f"{where}: parameters must name at least one parameter")
    params = tuple(_check_param(str(name), raw, where) for name, raw in top.parameters.items())
    try:
        load_scenario(top.base, **top.reference)
    except ConfigError as exc:
        raise ConfigError(f"{where}: base/reference: {exc}") from exc
    return SearchSpace(top.base, tuple(sorted(top.reference.items())), params, where)


def load_space(path: str | os.PathLike | None = None) -> SearchSpace:
    """The space in the YAML file ``path``; None: the shipped default space."""
    if path is None:
        text = importlib.resources.files("roco_env.stress").joinpath(DEFAULT_SPACE).read_text()
        return parse_space(load_yaml(text), where=f"roco_env/stress/{DEFAULT_SPACE}")
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"--space: no such file: {path}")
    return parse_space(load_yaml(path.read_text()), where=str(path))


def suggest(trial: Any, space: SearchSpace) -> dict[str, Any]:
    """The parameter values an Optuna ``trial`` draws from ``space``, in the space's order."""
    values: dict[str, Any] = {}
    for p in space.params:
        if p.type == "categorical":
            values[p.name] = trial.suggest_categorical(p.name, list(p.choices))
        elif p.type == "int":
            values[p.name] = trial.suggest_int(p.name, int(p.low), int(p.high), log=p.log)
        else:
            values[p.name] = trial.suggest_float(p.name, p.low, p.high, log=p.log)
    return values


def lane_density(fill: float, min_gap: float) -> float:
    """Vehicles per 100 m of lane at ``fill`` of the capacity 100 / (CAR_LENGTH + min_gap m)."""
    return fill * 100.0 / (CAR_LENGTH + min_gap)


def scenario_for(space: SearchSpace, values: dict[str, Any], name: str) -> ScenarioConfig:
    """The validated scenario of one evaluation: the base with ``values`` applied."""
    base = load_scenario(space.base)
    overrides = {k: v for k, v in values.items() if k != FILL}
    if FILL in values:  # one validation: the density's meaning depends on the layout
        layout = values.get("traffic.layout", base.traffic.layout)
        min_gap = values.get("traffic.min_gap", base.traffic.min_gap)
        overrides["traffic.density"] = float(
            values[FILL] if layout == "parking_lot" else lane_density(values[FILL], min_gap))
    config = apply_overrides(base, overrides)
    return dataclasses.replace(config, name=name, description=(
        "Found by roco-env stress: " + ", ".join(f"{k}={_text(v)}" for k, v in values.items())))


def _text(value: Any) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def param_value(config: ScenarioConfig, name: str) -> Any:
    """The value parameter ``name`` has in ``config`` (``fill`` computed back from the
    traffic density, see :func:`lane_density`)."""
    if name == FILL:
        traffic = config.traffic
        if traffic.layout == "parking_lot":
            return min(traffic.density, 1.0)
        return traffic.density * (CAR_LENGTH + traffic.min_gap) / 100.0
    node: Any = config
    for part in name.split("."):
        node = getattr(node, part)
    return node


def reference_scenario(space: SearchSpace) -> ScenarioConfig:
    """The default scene: the base with the space's reference overrides."""
    config = load_scenario(space.base, **dict(space.reference))
    return dataclasses.replace(config, name="reference",
                               description=f"{space.base} with {dict(space.reference)}")
