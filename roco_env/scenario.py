"""Scenario configuration: the schema, YAML loading and validated overrides.

A scenario file in ``scenarios/`` is a YAML mapping whose keys mirror the
dataclasses below. Every key is checked: an unknown key, a wrong type or an
out-of-range value raises :class:`ConfigError` naming the file, the key and
what is allowed. Overrides (``roco_env.parallel_env(scenario, **overrides)``)
use the same checks; they accept dotted names (``traffic.min_gap=1.0``) and the
stable top-level aliases in :data:`ALIASES` (``sigma_t=0.4``).
"""

from __future__ import annotations

import dataclasses
import importlib.resources
import os
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import partial
from numbers import Real
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from roco_env.schema import (
    ConfigError,
    build,
    check_value,
    load_yaml,
    spec,
    unknown_key_message,
)
from roco_env.stages import SCENARIO_FIELDS, available_stages, checked_params

SCENARIO_DIR_ENV = "ROCO_ENV_SCENARIOS"


_spec = spec

# traffic.layout values each traffic.source understands (replay/frames ignore the layout).
SOURCE_LAYOUTS: dict[str, tuple[str, ...]] = {
    "synthetic": ("highway", "intersection", "roundabout", "parking_lot", "traffic_jam"),
    "highway_env": ("highway", "merge", "roundabout", "intersection"),
}
LAYOUTS: tuple[str, ...] = tuple(dict.fromkeys(sum(SOURCE_LAYOUTS.values(), ())))
# The layouts whose traffic traffic.density sizes (a replay's vehicles come from its files;
# highway-env's merge and roundabout are fixed scenes).
DENSITY_LAYOUTS: dict[str, tuple[str, ...]] = {
    "synthetic": SOURCE_LAYOUTS["synthetic"],
    "highway_env": ("highway", "intersection"),
}


@dataclass
class TrafficConfig:
    """Where the vehicles come from and how crowded the scene is."""

    source: str = _spec("synthetic", choices=partial(available_stages, "traffic"),
                        doc="the traffic stage (roco_env.stages): synthetic | highway_env | "
                        "opv2v | dair | frames | a registered one")
    layout: str = _spec(
        "intersection",
        choices=LAYOUTS,
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
    path: str | None = _spec(None, path=True, doc="dataset folder for opv2v/dair replay")
    params: dict = _spec({}, doc="the source's parameters (highway_env: extra env config)")


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
    """Pose noise (see roco_env.noise); sigmas are standard deviations."""

    model: str = _spec("gaussian", choices=partial(available_stages, "noise"),
                       doc="the pose-noise stage (roco_env.noise, roco_env.stages)")
    sigma_t: float = _spec(0.2, low=0.0, high=20.0, doc="translation std, m")
    sigma_r: float = _spec(0.2, low=0.0, high=45.0, doc="rotation std, degrees")
    perturb_ego: bool = _spec(True)
    per_agent: dict = _spec({}, doc="agent id -> [sigma_t, sigma_r] overriding the levels")
    params: dict = _spec({}, doc="the model's parameters (its dataclass), checked on load")


@dataclass
class DetectorConfig:
    """What each agent detects (see roco_env.sensing.detector)."""

    preset: str = _spec("realistic", choices=partial(available_stages, "detector"),
                        doc="the detector stage (roco_env.sensing, roco_env.stages)")
    params: dict = _spec({}, doc="the preset's parameters (its dataclass) overriding its "
                         "defaults, checked on load")


@dataclass
class FusionConfig:
    method: str = _spec("late", choices=partial(available_stages, "fusion"),
                        doc="intermediate decodes fused BEV feature maps: needs detector.preset "
                        "learned; none scores the ego's own boxes alone (the no-fusion "
                        "reference)")
    nms_iou: float = _spec(0.15, low=0.0, high=1.0, doc="BEV IoU threshold of late-fusion NMS")
    params: dict = _spec({}, doc="the method's parameters (a registered method's dataclass)")


@dataclass
class FeaturesConfig:
    enabled: bool = _spec(False)
    resolution: float = _spec(0.4, low=0.05, high=5.0, doc="BEV cell size, m")


# Ground-truth conventions (roco_env.evaluation.ground_truths, docs/metrics.md).
GROUND_TRUTHS: tuple[str, ...] = ("visible", "opencood")
# What an agent's action means (roco_env.action_modes implements each).
ACTION_MODES: tuple[str, ...] = ("correction", "residual", "select", "gate")
# What an agent observes (roco_env.observation_modes implements each).
OBSERVATION_MODES: tuple[str, ...] = ("raw", "aligned", "bev")


@dataclass
class EvaluationConfig:
    x_range: list = _spec([-140.8, 140.8], doc="ego-frame evaluation range along x, m")
    y_range: list = _spec([-40.0, 40.0], doc="ego-frame evaluation range along y, m")
    reward: str = _spec("ap70", choices=partial(available_stages, "reward"),
                        doc="the per-step reward stage (roco_env.evaluation, roco_env.stages)")
    reward_params: dict = _spec({}, doc="the reward's parameters (a registered reward's "
                                "dataclass)")
    ground_truth: str = _spec("visible", choices=GROUND_TRUTHS,
                              doc="visible: what the collaboration sees, own car out; opencood: "
                                  "every vehicle in range, own car in, z_range applies")
    z_range: list = _spec([-3.0, 1.0], doc="ego-LiDAR-frame z range of the opencood ground "
                                           "truth (every box corner inside), m")


@dataclass
class ActionConfig:
    """What an agent's action means (roco_env.action_modes; docs/learning.md)."""

    mode: str = _spec("correction", choices=ACTION_MODES,
                      doc="correction: (dx, dy, dyaw) per slot; residual: a scaled residual on "
                      "the base aligner's pose; select: one of the choices or reject per slot; "
                      "gate: keep the base aligner's pose or reject per slot")
    max_translation: float = _spec(15.0, low=0.0, high=20.0, low_open=True,
                                   doc="correction mode: the action space's |dx|, |dy| bound, m")
    max_rotation: float = _spec(15.0, low=0.0, high=180.0, low_open=True,
                                doc="correction mode: the action space's |dyaw| bound, degrees")
    base: str = _spec("roco", doc="residual and gate modes: the policy spec run first")
    choices: list = _spec(["identity", "coalign", "roco", "roco_antialias"],
                          doc="select mode: the policy specs chosen among (index len(choices) "
                          "rejects)")
    scale: list = _spec([1.0, 1.0, 1.0], doc="residual mode: the residual of action 1, "
                        "(dx m, dy m, dyaw degrees)")


@dataclass
class ObservationConfig:
    """What an agent observes (roco_env.observation_modes; docs/learning.md)."""

    mode: str = _spec("raw", choices=OBSERVATION_MODES,
                      doc="raw: own and collaborators' boxes in their own frames; aligned: "
                      "collaborators' boxes in the ego frame plus the base aligner's per-slot "
                      "diagnostics; bev: occupancy rasters of the ego and each collaborator")
    bev_range: float = _spec(40.0, low=5.0, high=200.0,
                             doc="bev mode: half side of the square raster around the ego, m")
    bev_resolution: float = _spec(1.0, low=0.1, high=10.0,
                                  doc="bev mode: raster cell side, m")


# Bytes of a message's fixed header (sender, scan time, pose, box count, feature codec):
# the payload encoder of roco_env.comm.payload writes exactly these (a test checks it).
MESSAGE_HEADER_BYTES = 44
# How a message carries a feature map (roco_env.comm.payload): every cell or only the
# non-zero ones (with their indices), as 32- or 16-bit floats.
FEATURE_CODECS: tuple[str, ...] = ("dense_f32", "dense_f16", "sparse_f32", "sparse_f16")
# What the receiving ego does about a late message's moving boxes (roco_env.comm.delivery).
COMPENSATIONS: tuple[str, ...] = ("none", "track")


@dataclass
class CommConfig:
    """The network between the collaborators' messages and the ego (roco_env.comm,
    docs/network.md). The defaults switch it off: every message arrives at once, whole."""

    delay: str = _spec("none", choices=partial(available_stages, "delay"),
                       doc="the delay stage (roco_env.comm.delay): none | fixed | uniform | "
                       "opencood | distance | a registered one")
    delay_params: dict = _spec({}, doc="the delay model's parameters (its dataclass)")
    loss: str = _spec("none", choices=partial(available_stages, "loss"),
                      doc="the loss stage (roco_env.comm.loss): none | bernoulli | "
                      "gilbert_elliott | a registered one")
    loss_params: dict = _spec({}, doc="the loss model's parameters (its dataclass)")
    budget_bytes: int | None = _spec(
        None, low=MESSAGE_HEADER_BYTES, high=10**9,
        doc=f"per-link budget of one message, bytes (at least the {MESSAGE_HEADER_BYTES}-byte "
        "header); what does not fit is dropped: the lowest-scoring boxes first, then feature "
        "cells by magnitude; null = unlimited")
    feature_codec: str = _spec("dense_f32", choices=FEATURE_CODECS,
                               doc="how a feature map is sent: every cell (dense) or the "
                               "non-zero cells with their indices (sparse), 32- or 16-bit")
    sensor_offset_ms: dict = _spec({}, doc="agent id -> ms by which its LiDAR sweep ends "
                                   "before the receiving ego's, in [0, 500]")
    max_age_ms: float = _spec(1000.0, low=0.0, high=60000.0, low_open=True,
                              doc="an ego drops a collaborator's message older than this, ms")
    compensation: str = _spec("none", choices=COMPENSATIONS,
                              doc="none: each slot's boxes as sent; track: the ego tracks each "
                              "collaborator's boxes over its messages and moves them to its "
                              "own time, for alignment and fusion")


@dataclass
class AttackConfig:
    """Collaborators that lie in what they send (roco_env.attacks; docs/attacks.md)."""

    kind: str = _spec("none", choices=partial(available_stages, "attack"),
                      doc="the attack stage (roco_env.attacks, roco_env.stages): none | "
                      "pose_spoof | ghost | erase | learned | a registered one")
    agents: list = _spec([], doc="the attackers' agent ids; empty = `count` agents drawn "
                         "per episode from the seed")
    count: int = _spec(1, low=1, high=32, doc="attackers drawn per episode when `agents` is "
                       "empty")
    params: dict = _spec({}, doc="the attack's parameters (its dataclass), checked on load")


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
    action: ActionConfig = field(default_factory=ActionConfig)
    observation: ObservationConfig = field(default_factory=ObservationConfig)
    comm: CommConfig = field(default_factory=CommConfig)
    attack: AttackConfig = field(default_factory=AttackConfig)
    max_boxes: int = _spec(64, low=1, high=1024, doc="K: padded boxes per agent in observations")
    max_collaborators: int = _spec(5, low=0, high=32, doc="N: collaborator slots per ego")
    max_objects: int = _spec(256, low=1, high=4096,
                             doc="M: ground-truth box slots of the global state()")


# Stable top-level override names (the env's Arguments) -> dotted field paths.
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
    "delay": "comm.delay",
    "delay_ms": "comm.delay_params.delay_ms",
    "loss": "comm.loss",
    "loss_rate": "comm.loss_params.loss_rate",
}


def library_dir() -> Path:
    """The shipped scenario library, package data ``roco_env/scenarios``.

    In the repository ``roco_env/scenarios`` links to the top-level ``scenarios/``
    folder (the editable source); a wheel holds the YAML files themselves.
    """
    return Path(str(importlib.resources.files("roco_env") / "scenarios"))


def scenario_dirs() -> list[Path]:
    """Folders searched for ``<name>.yaml``: $ROCO_ENV_SCENARIOS, then the shipped library."""
    dirs = [Path(p) for p in os.environ.get(SCENARIO_DIR_ENV, "").split(os.pathsep) if p]
    dirs.append(library_dir())
    return dirs


def list_scenarios() -> list[str]:
    """Names of the scenario YAML files available (sorted)."""
    names = {p.stem for d in scenario_dirs() if d.is_dir() for p in d.glob("*.yaml")}
    return sorted(names)


def scenario_path(name_or_path: str | os.PathLike) -> Path:
    """Resolve a scenario name (``urban_intersection``) or a YAML path to a file."""
    if not isinstance(name_or_path, (str, os.PathLike)):
        raise ConfigError("scenario must be a name from roco_env.list_scenarios() or a .yaml "
                            f"path; got {name_or_path!r} ({type(name_or_path).__name__})")
    candidate = Path(name_or_path)
    if candidate.is_dir():
        raise ConfigError(f"{candidate} is a folder, not a scenario .yaml file")
    if candidate.suffix in (".yaml", ".yml") or candidate.exists():
        if not candidate.is_file():
            raise ConfigError(f"scenario file {candidate} does not exist")
        return candidate
    for folder in scenario_dirs():
        path = folder / f"{name_or_path}.yaml"
        if path.is_file():
            return path
    raise ConfigError(
        f"unknown scenario {str(name_or_path)!r}; available: {', '.join(list_scenarios())} "
        "(or give a path to a .yaml file)"
    )


def load_scenario(name_or_path: str | os.PathLike = "urban_intersection",
                  **overrides: Any) -> ScenarioConfig:
    """Load and validate a scenario, then apply validated overrides.

    Relative paths in the file (``traffic.path``, ``detector.params.weights``: every field
    declared ``path=True``) are relative to the file's folder; relative paths in
    ``overrides`` stay relative to the working directory."""
    path = scenario_path(name_or_path)
    try:
        raw = load_yaml(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start}); "
                            "save the scenario file as UTF-8") from exc
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: malformed YAML: {exc}") from exc
    if raw is None:
        raise ConfigError(f"{path}: the file is empty; a scenario needs at least one key "
                            "(see the shipped scenarios for every field)")
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: top level must be a mapping of keys, got {type(raw).__name__}")
    raw.setdefault("name", path.stem)
    config = _build_scenario(raw, where=str(path), base=path.parent)
    return apply_overrides(config, overrides)


def scenario_from_dict(data: Mapping[str, Any], where: str = "<dict>") -> ScenarioConfig:
    """Validate a plain mapping into a config.

    The keys are those of the YAML files (``{"traffic": {"density": 5}, "agents":
    {"cavs": 3}}``); a missing key keeps its default. Raises :class:`ConfigError`
    naming ``where``, the key and the allowed values, as :func:`load_scenario` does.
    """
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where}: a scenario mapping needs the YAML keys (traffic, agents, "
                            f"...); got {type(data).__name__} ({data!r})")
    return _build_scenario(dict(data), where=where)


def scenario_to_dict(config: ScenarioConfig) -> dict:
    """Plain nested dict of a config, every field included; ``scenario_from_dict`` of it
    (or the YAML :func:`save_scenario` writes) gives the same config back."""
    if not isinstance(config, ScenarioConfig):
        raise ConfigError("a ScenarioConfig is needed (load_scenario(name) or "
                            f"scenario_from_dict(mapping)); got {type(config).__name__}")
    return dataclasses.asdict(config)


def save_scenario(config: ScenarioConfig, path: str | os.PathLike) -> Path:
    """Write ``config`` as a scenario YAML file (every field) and return its path.

    The file loads back equal with :func:`load_scenario` and can be passed to
    ``roco_env.parallel_env`` or ``roco-env compare --scenario``.
    """
    path = scenario_file_name(path, "save_scenario")
    path.write_text(yaml.safe_dump(scenario_to_dict(config), sort_keys=False))
    return path


def scenario_file_name(path: str | os.PathLike, who: str) -> Path:
    """``path`` as a Path if it names a scenario file (.yaml or .yml), else a ConfigError
    naming ``who`` (the caller about to write it): the library lists only such files."""
    path = Path(path)
    if path.suffix not in (".yaml", ".yml"):
        raise ConfigError(f"{who}: {path} must end in .yaml or .yml")
    return path


def apply_overrides(config: ScenarioConfig, overrides: dict[str, Any]) -> ScenarioConfig:
    """Return a copy of ``config`` with dotted-name or alias overrides applied and validated."""
    data = scenario_to_dict(config)
    base_density = config.traffic.density
    fields: dict[str, str] = {}  # override key -> the dotted field it sets
    for key, value in overrides.items():
        dotted = ALIASES.get(key, key)
        for other, other_dotted in fields.items():
            if f"{dotted}.".startswith(f"{other_dotted}.") \
                    or f"{other_dotted}.".startswith(f"{dotted}."):
                outer = min(dotted, other_dotted, key=len)
                raise ConfigError(f"override: {other!r} and {key!r} both set {outer}; give one")
        fields[key] = dotted
        parts = dotted.split(".")
        node = data
        for depth, part in enumerate(parts[:-1]):
            if not isinstance(node.get(part), dict):
                raise ConfigError(unknown_key_message("override", ".".join(parts[: depth + 1]),
                                                         _valid_override_names()))
            node = node[part]
        if parts[-1] not in node and ".".join(parts[:-1]) not in _mapping_fields():
            raise ConfigError(unknown_key_message("override", key, _valid_override_names()))
        node[parts[-1]] = value
    config = _build_scenario(data, where="override")
    traffic = config.traffic
    # the scene's own value is no change (a sweep may pass every scene its density)
    if "traffic.density" in fields.values() and traffic.density != base_density \
            and traffic.layout not in DENSITY_LAYOUTS.get(traffic.source, ()):
        scene = f" with layout {traffic.layout!r}" if traffic.source in DENSITY_LAYOUTS else ""
        raise ConfigError(
            f"override: traffic.density has no effect with traffic.source={traffic.source!r}"
            f"{scene}; leave it out (it sizes the traffic of " + ", ".join(
                f"{source!r} ({' | '.join(layouts)})" for source, layouts in DENSITY_LAYOUTS.items())
            + ")")
    return config


def _build_scenario(data: dict, where: str, base: Path | None = None) -> ScenarioConfig:
    """The config of ``data`` with every field checked, then the rules that join fields;
    relative path fields joined to ``base`` (a scenario file's folder) when given."""
    config = build(ScenarioConfig, data, where=where, base=base)
    traffic = config.traffic
    allowed = SOURCE_LAYOUTS.get(traffic.source)
    if allowed is not None and traffic.layout not in allowed:
        raise ConfigError(
            f"{where}: traffic.layout={traffic.layout!r} is not allowed with "
            f"traffic.source={traffic.source!r}; choose one of {list(allowed)}"
        )
    if traffic.source == "synthetic" and traffic.layout == "parking_lot" \
            and traffic.density > 1.0:
        raise ConfigError(
            f"{where}: traffic.density={traffic.density!r} is out of range for layout "
            "'parking_lot', where it is the fill ratio of the stalls; allowed [0, 1]")
    if traffic.source == "highway_env" and config.agents.cavs < 1:
        raise ConfigError(f"{where}: agents.cavs must be >= 1 with traffic.source="
                            "'highway_env' (its controlled vehicle is a CAV); got 0")
    for name in ("x_range", "y_range", "z_range"):
        setattr(config.evaluation, name,
                _check_range(getattr(config.evaluation, name), where, f"evaluation.{name}"))
    config.noise.per_agent = _per_agent_levels(config.noise.per_agent, where)
    config.comm.sensor_offset_ms = _sensor_offsets(config.comm.sensor_offset_ms, where)
    config.action.scale = _check_scale(config.action.scale, where)
    config.action.choices = _check_choices(config.action.choices, where)
    for kind in SCENARIO_FIELDS:
        _check_stage_params(config, kind, where, base)
    if config.fusion.method == "intermediate" and config.detector.preset != "learned":
        raise ConfigError(
            f"{where}: fusion.method='intermediate' fuses and decodes the learned detector's BEV "
            f"feature maps, so it needs detector.preset='learned' (detector='learned'); got "
            f"detector.preset={config.detector.preset!r}"
        )
    if config.comm.sensor_offset_ms and config.fusion.method == "intermediate":
        raise ConfigError(
            f"{where}: comm.sensor_offset_ms moves a sender's boxes to the earlier instant of its "
            "sweep, which a feature map cannot follow, so it needs fusion.method='late'; got "
            "fusion.method='intermediate' (leave comm.sensor_offset_ms empty)")
    gate = config.detector.params.get("gate") if config.detector.preset == "learned" else None
    if gate is not None and config.fusion.method != "intermediate":
        raise ConfigError(
            f"{where}: detector.params.gate={gate!r} chooses how intermediate fusion fuses the "
            f"feature maps, so it needs fusion.method='intermediate'; got "
            f"fusion.method={config.fusion.method!r} (with it leave the gate unset, or set "
            f"detector.params.gate=null)"
        )
    return config


def _check_stage_params(config: ScenarioConfig, kind: str, where: str,
                        base: Path | None) -> None:
    """Check (in place) the parameters the scenario gives the implementation it names for
    stage ``kind`` (roco_env.stages.checked_params)."""
    section_name, choice_field, params_field = SCENARIO_FIELDS[kind]
    section = getattr(config, section_name)
    setattr(section, params_field, checked_params(
        kind, getattr(section, choice_field), getattr(section, params_field), where, base))


def _per_agent_levels(per_agent: dict, where: str) -> dict:
    """noise.per_agent (agent id -> [sigma_t m, sigma_r deg]) with each level checked
    against the bounds of noise.sigma_t / noise.sigma_r (an agent's level is one of
    theirs); the agent ids are checked when the env knows its agents."""
    bounds = {f.name: f.metadata for f in dataclasses.fields(NoiseConfig)}
    checked = {}
    for agent, pair in per_agent.items():
        key = f"noise.per_agent.{agent}"
        if not isinstance(pair, (list, tuple)) or len(pair) != 2:
            raise ConfigError(f"{where}: {key} must be [sigma_t m, sigma_r deg]; got {pair!r}")
        checked[agent] = [check_value(value, float, bounds[name], where, f"{key}[{k}] ({name})")
                          for k, (value, name) in enumerate(zip(pair, ("sigma_t", "sigma_r"),
                                                                strict=True))]
    return checked


def _sensor_offsets(offsets: dict, where: str) -> dict:
    """comm.sensor_offset_ms (agent id -> ms) with each offset a number in [0, 500]; the
    agent ids are checked when the env knows its agents."""
    meta = {"low": 0.0, "high": 500.0}
    return {agent: check_value(value, float, meta, where, f"comm.sensor_offset_ms.{agent}")
            for agent, value in offsets.items()}


def _check_scale(value: list, where: str) -> list[float]:
    """action.scale as three finite numbers > 0 (m, m, degrees), else a ConfigError."""
    ok = isinstance(value, list) and len(value) == 3 and all(
        isinstance(v, Real) and not isinstance(v, bool) and np.isfinite(v) and v > 0
        for v in value)
    if not ok:
        raise ConfigError(f"{where}: action.scale must be three finite numbers > 0, the "
                            f"residual of action 1 as [dx m, dy m, dyaw degrees]; got {value!r}")
    return [float(v) for v in value]


def _check_choices(value: list, where: str) -> list[str]:
    """action.choices as a non-empty list of distinct policy-spec strings, else a ConfigError
    (the policies themselves are checked when an env builds them)."""
    ok = isinstance(value, list) and value and all(isinstance(v, str) and v for v in value)
    if not ok or len(set(value)) != len(value):
        raise ConfigError(f"{where}: action.choices must be a non-empty list of distinct "
                            f"policy specs (e.g. [identity, coalign, roco]); got {value!r}")
    return list(value)


def _check_range(value: list, where: str, key: str) -> list[float]:
    """[low, high] as floats (numpy numbers accepted) with low < high."""
    numbers = len(value) == 2 and all(isinstance(v, Real) and not isinstance(v, (bool, np.bool_))
                                      for v in value)
    if not numbers or not value[0] < value[1]:
        raise ConfigError(f"{where}: {key} must be [low, high] in m with low < high; "
                            f"got {value!r}")
    return [float(v) for v in value]


def _mapping_fields() -> set[str]:
    """Dotted names of the fields holding a free mapping (``noise.params``,
    ``comm.sensor_offset_ms``, ...): an override may add a key below them."""
    return {f"{top.name}.{name}" for top in dataclasses.fields(ScenarioConfig)
            if top.default_factory is not dataclasses.MISSING
            and dataclasses.is_dataclass(top.default_factory)
            for name, hint in typing.get_type_hints(top.default_factory).items()
            if hint is dict}


def _valid_override_names() -> list[str]:
    names = list(ALIASES)
    for top in dataclasses.fields(ScenarioConfig):
        if dataclasses.is_dataclass(top.default_factory if top.default_factory
                                    is not dataclasses.MISSING else None):
            names += [f"{top.name}.{f.name}" for f in dataclasses.fields(top.default_factory)]
        else:
            names.append(top.name)
    return names
