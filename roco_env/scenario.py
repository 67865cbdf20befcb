"""Scenario configuration: the schema, YAML loading and validated overrides.

A scenario file in ``scenarios/`` is a YAML mapping whose keys mirror the
dataclasses below. Every key is checked: an unknown key, a wrong type or an
out-of-range value raises :class:`ScenarioError` naming the file, the key and
what is allowed. Overrides (``roco_env.parallel_env(scenario, **overrides)``)
use the same checks; they accept dotted names (``traffic.min_gap=1.0``) and the
stable top-level aliases in :data:`ALIASES` (``sigma_t=0.4``).
"""

from __future__ import annotations

import dataclasses
import os
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

SCENARIO_DIR_ENV = "ROCO_ENV_SCENARIOS"


class ScenarioError(ValueError):
    """A scenario file or override is invalid; the message names where and why."""


def _spec(default: Any, *, choices: tuple | None = None, low: float | None = None,
          high: float | None = None, doc: str = "") -> Any:
    """A dataclass field carrying its allowed values (choices or [low, high])."""
    meta = {"choices": choices, "low": low, "high": high, "doc": doc}
    if isinstance(default, (list, dict, tuple)):
        return field(default_factory=lambda: type(default)(default), metadata=meta)
    return field(default=default, metadata=meta)


@dataclass
class TrafficConfig:
    """Where the vehicles come from and how crowded the scene is."""

    source: str = _spec("synthetic", choices=("synthetic", "highway_env", "opv2v", "dair", "frames"))
    layout: str = _spec(
        "intersection",
        choices=("highway", "intersection", "roundabout", "parking_lot", "traffic_jam", "merge"),
        doc="synthetic: highway|intersection|roundabout|parking_lot|traffic_jam; "
        "highway_env: highway|merge|roundabout|intersection",
    )
    density: float = _spec(
        3.0, low=0.0, high=100.0,
        doc="vehicles per 100 m of lane; for parking_lot the fill ratio in [0, 1]",
    )
    min_gap: float = _spec(2.0, low=0.0, high=50.0, doc="minimum bumper-to-bumper gap, m")
    lanes: int = _spec(
        3, low=1, high=8,
        doc="lanes per direction (roundabout: ring lanes, at most 2; parking_lot: double rows)",
    )
    length: float = _spec(
        300.0, low=20.0, high=5000.0,
        doc="road length, m (intersection/roundabout: across the scene; parking_lot: row "
        "length, at most 200 m)",
    )
    dt: float = _spec(0.1, low=0.01, high=1.0, doc="simulation step, s")
    speed_limit: float | None = _spec(
        None, low=0.5, high=60.0, doc="desired speed, m/s; null = the layout's default"
    )
    path: str | None = _spec(None, doc="dataset folder for opv2v/dair replay")
    params: dict = _spec(
        {}, doc="source-specific options (highway_env: extra env config; replay: see traffic)"
    )


@dataclass
class AgentsConfig:
    """Who collaborates: CAVs and RSUs, their sensors and radios."""

    cavs: int = _spec(4, low=0, high=32)
    rsus: int = _spec(0, low=0, high=8)
    cav_range: float = _spec(70.0, low=1.0, high=300.0, doc="CAV sensor range, m")
    rsu_range: float = _spec(100.0, low=1.0, high=300.0, doc="RSU sensor range, m")
    comm_range: float = _spec(70.0, low=1.0, high=1000.0, doc="V2X communication range, m")
    cav_height: float = _spec(1.9, low=0.0, high=10.0, doc="CAV LiDAR height, m")
    rsu_height: float = _spec(5.5, low=0.0, high=20.0, doc="RSU LiDAR height, m")
    evaluated: list | None = _spec(None, doc="agent ids evaluated as egos; null = all")


@dataclass
class NoiseConfig:
    """Pose noise (DESIGN.md section 4); sigmas are standard deviations."""

    model: str = _spec(
        "gaussian", choices=("gaussian", "laplace", "bias", "drift", "ar1", "localization")
    )
    sigma_t: float = _spec(0.2, low=0.0, high=20.0, doc="translation std, m")
    sigma_r: float = _spec(0.2, low=0.0, high=45.0, doc="rotation std, degrees")
    perturb_ego: bool = _spec(True)
    per_agent: dict = _spec({}, doc="agent id -> [sigma_t, sigma_r] overriding the levels")
    params: dict = _spec({}, doc="model-specific parameters (e.g. ar1 rho, localization GNSS)")


@dataclass
class DetectorConfig:
    """What each agent detects (DESIGN.md section 5)."""

    preset: str = _spec("realistic", choices=("ideal", "realistic", "learned"))
    params: dict = _spec({}, doc="explicit detector parameters overriding the preset "
                         "(learned: weights, device, score_threshold)")


@dataclass
class FusionConfig:
    method: str = _spec("late", choices=("late", "intermediate"),
                        doc="intermediate decodes fused BEV feature maps: needs detector.preset "
                        "learned")
    nms_iou: float = _spec(0.15, low=0.0, high=1.0, doc="BEV IoU threshold of late-fusion NMS")


@dataclass
class FeaturesConfig:
    enabled: bool = _spec(False)
    resolution: float = _spec(0.4, low=0.05, high=5.0, doc="BEV cell size, m")


# Per-step reward kinds (roco_env.evaluation.reward computes them).
REWARDS: tuple[str, ...] = ("ap30", "ap50", "ap70", "neg_rpe")


@dataclass
class EvaluationConfig:
    x_range: list = _spec([-140.8, 140.8], doc="ego-frame evaluation range along x, m")
    y_range: list = _spec([-40.0, 40.0], doc="ego-frame evaluation range along y, m")
    reward: str = _spec("ap70", choices=REWARDS)


@dataclass
class ScenarioConfig:
    name: str = _spec("custom")
    description: str = _spec("")
    traffic: TrafficConfig = field(default_factory=TrafficConfig)
    agents: AgentsConfig = field(default_factory=AgentsConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    fusion: FusionConfig = field(default_factory=FusionConfig)
    features: FeaturesConfig = field(default_factory=FeaturesConfig)
    evaluation: EvaluationConfig = field(default_factory=EvaluationConfig)
    max_boxes: int = _spec(64, low=1, high=1024, doc="K: padded boxes per agent in observations")
    max_collaborators: int = _spec(5, low=0, high=32, doc="N: collaborator slots per ego")


# Stable top-level override names (DESIGN.md section 9) -> dotted field paths.
ALIASES: dict[str, str] = {
    "sigma_t": "noise.sigma_t",
    "sigma_r": "noise.sigma_r",
    "noise_model": "noise.model",
    "density": "traffic.density",
    "cavs": "agents.cavs",
    "rsus": "agents.rsus",
    "detector": "detector.preset",
    "fusion": "fusion.method",
    "reward": "evaluation.reward",
    "features": "features.enabled",
}


def scenario_dirs() -> list[Path]:
    """Folders searched for ``<name>.yaml``: $ROCO_ENV_SCENARIOS, then the repo's scenarios/."""
    dirs = [Path(p) for p in os.environ.get(SCENARIO_DIR_ENV, "").split(os.pathsep) if p]
    dirs.append(Path(__file__).resolve().parents[1] / "scenarios")
    return dirs


def list_scenarios() -> list[str]:
    """Names of the scenario YAML files available (sorted)."""
    names = {p.stem for d in scenario_dirs() if d.is_dir() for p in d.glob("*.yaml")}
    return sorted(names)


def scenario_path(name_or_path: str | os.PathLike) -> Path:
    """Resolve a scenario name (``urban_intersection``) or a YAML path to a file."""
    candidate = Path(name_or_path)
    if candidate.suffix in (".yaml", ".yml") or candidate.exists():
        if not candidate.is_file():
            raise ScenarioError(f"scenario file {candidate} does not exist")
        return candidate
    for folder in scenario_dirs():
        path = folder / f"{name_or_path}.yaml"
        if path.is_file():
            return path
    raise ScenarioError(
        f"unknown scenario {str(name_or_path)!r}; available: {', '.join(list_scenarios())} "
        "(or give a path to a .yaml file)"
    )


def load_scenario(name_or_path: str | os.PathLike = "urban_intersection",
                  **overrides: Any) -> ScenarioConfig:
    """Load and validate a scenario, then apply validated overrides."""
    path = scenario_path(name_or_path)
    try:
        raw = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ScenarioError(f"{path}: malformed YAML: {exc}") from exc
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        raise ScenarioError(f"{path}: top level must be a mapping of keys, got {type(raw).__name__}")
    raw.setdefault("name", path.stem)
    config = _build_scenario(raw, where=str(path))
    return apply_overrides(config, overrides)


def scenario_from_dict(data: dict, where: str = "<dict>") -> ScenarioConfig:
    """Validate a plain mapping (same keys as the YAML files) into a config."""
    return _build_scenario(dict(data), where=where)


def scenario_to_dict(config: ScenarioConfig) -> dict:
    """Plain nested dict (YAML-ready) of a config."""
    return dataclasses.asdict(config)


def apply_overrides(config: ScenarioConfig, overrides: dict[str, Any]) -> ScenarioConfig:
    """Return a copy of ``config`` with dotted-name or alias overrides applied and validated."""
    data = scenario_to_dict(config)
    for key, value in overrides.items():
        dotted = ALIASES.get(key, key)
        parts = dotted.split(".")
        node = data
        for depth, part in enumerate(parts[:-1]):
            if not isinstance(node.get(part), dict):
                raise ScenarioError(_unknown_key_message("override", ".".join(parts[: depth + 1]),
                                                         _valid_override_names()))
            node = node[part]
        if parts[-1] not in node:
            raise ScenarioError(_unknown_key_message("override", key, _valid_override_names()))
        node[parts[-1]] = value
    return _build_scenario(data, where="override")


# traffic.layout values each traffic.source understands (replay/frames ignore the layout).
SOURCE_LAYOUTS: dict[str, tuple[str, ...]] = {
    "synthetic": ("highway", "intersection", "roundabout", "parking_lot", "traffic_jam"),
    "highway_env": ("highway", "merge", "roundabout", "intersection"),
}


def _build_scenario(data: dict, where: str) -> ScenarioConfig:
    config = _build(ScenarioConfig, data, where=where, prefix="")
    allowed = SOURCE_LAYOUTS.get(config.traffic.source)
    if allowed is not None and config.traffic.layout not in allowed:
        raise ScenarioError(
            f"{where}: traffic.layout={config.traffic.layout!r} is not allowed with "
            f"traffic.source={config.traffic.source!r}; choose one of {list(allowed)}"
        )
    if config.fusion.method == "intermediate" and config.detector.preset != "learned":
        raise ScenarioError(
            f"{where}: fusion.method='intermediate' fuses and decodes the learned detector's BEV "
            f"feature maps, so it needs detector.preset='learned' (detector='learned'); got "
            f"detector.preset={config.detector.preset!r}"
        )
    return config


def _valid_override_names() -> list[str]:
    names = list(ALIASES)
    for top in dataclasses.fields(ScenarioConfig):
        if dataclasses.is_dataclass(top.default_factory if top.default_factory
                                    is not dataclasses.MISSING else None):
            names += [f"{top.name}.{f.name}" for f in dataclasses.fields(top.default_factory)]
        else:
            names.append(top.name)
    return names


def _unknown_key_message(where: str, key: str, allowed: list[str]) -> str:
    return f"{where}: unknown key {key!r}; allowed: {', '.join(allowed)}"


def _build(cls: type, data: dict, where: str, prefix: str) -> Any:
    if not isinstance(data, dict):
        raise ScenarioError(f"{where}: {prefix.rstrip('.') or 'top level'} must be a mapping")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    hints = typing.get_type_hints(cls)
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ScenarioError(_unknown_key_message(where, prefix + unknown[0],
                                                 [prefix + name for name in fields]))
    values = {}
    for name, value in data.items():
        key, hint = prefix + name, hints[name]
        if dataclasses.is_dataclass(hint):
            values[name] = _build(hint, value, where, key + ".")
        else:
            values[name] = _check_value(value, hint, fields[name].metadata, where, key)
    return cls(**values)


def _check_value(value: Any, hint: Any, meta: Any, where: str, key: str) -> Any:
    allowed_types = typing.get_args(hint) if isinstance(hint, types.UnionType) else (hint,)
    if value is None:
        if type(None) in allowed_types:
            return None
        raise ScenarioError(f"{where}: {key} must not be null")
    base = next(t for t in allowed_types if t is not type(None))
    if base is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if base is list and isinstance(value, tuple):
        value = list(value)
    if not isinstance(value, base) or (base in (int, float) and isinstance(value, bool)):
        raise ScenarioError(
            f"{where}: {key} must be of type {base.__name__}, got {type(value).__name__} ({value!r})"
        )
    choices, low, high = meta.get("choices"), meta.get("low"), meta.get("high")
    if choices is not None and value not in choices:
        raise ScenarioError(f"{where}: {key}={value!r} is not allowed; choose one of {list(choices)}")
    if low is not None and not (low <= value <= high):
        raise ScenarioError(f"{where}: {key}={value!r} is out of range; allowed [{low}, {high}]")
    return value
