"""Stage registries: every interchangeable part of the pipeline, found by name.

A scenario names one implementation per stage kind and gives it parameters (the
``{kind, params}`` pairs of :data:`SCENARIO_FIELDS`)::

    traffic:   {source: synthetic, params: {}}
    noise:     {model: ar1, params: {rho: 0.8}}
    detector:  {preset: realistic, params: {sigma_xy: 0.1}}
    fusion:    {method: late, params: {}}
    evaluation: {reward: ap70, reward_params: {}}
    comm:      {delay: fixed, delay_params: {delay_ms: 100},
                loss: bernoulli, loss_params: {loss_rate: 0.1}}
    attack:    {kind: none, params: {}}

The names a scenario accepts are the registry's; the parameters are checked by the
implementation's own parameter dataclass (declared with :func:`roco_env.schema.spec`,
next to the implementation), with the same messages as every other field.

What a factory of each kind is called with and returns (the protocols live with each
stage's code):

=========  ==================================================  ==========================
kind       factory(...)                                        returns
=========  ==================================================  ==========================
traffic    ``(config: ScenarioConfig, **inputs)``; inputs:     a ``TrafficSource``
           the user's ``frames=`` when given                   (roco_env.traffic.state)
noise      ``(config: NoiseConfig, agent_ids, dt)``            a ``PoseNoise`` (roco_env.noise)
detector   ``(config: DetectorConfig, region)``                a ``Detector`` protocol
                                                               (roco_env.sensing.detector)
fusion     ``(config: ScenarioConfig, detector)``              a ``Fusion`` (roco_env.fusion)
reward     ``(config: EvaluationConfig)``                      a ``Reward``
                                                               (roco_env.evaluation)
delay      ``(config: CommConfig)``                            a ``DelayModel``
                                                               (roco_env.comm.delay)
loss       ``(config: CommConfig)``                            a ``LossModel``
                                                               (roco_env.comm.loss)
attack     ``(config: ScenarioConfig, agent_ids)``             an ``Attack``
                                                               (roco_env.attacks)
=========  ==================================================  ==========================

Three ways make a name of your own selectable from a scenario YAML:

* ``roco_env.register_stage("detector", "mine", factory, params=MyParams)`` in your code
  (``factory`` a callable or an import target ``"my_pkg.module:make"``);
* an installed package's entry point in the group ``roco_env.<kind>``::

      [project.entry-points."roco_env.detector"]
      mine = "my_pkg.module:make"

  (the factory's ``PARAMS`` attribute, if any, declares its parameters, as policies do);
* nothing else: built-in names are fixed and a registration never replaces one.

``params``: a dataclass whose fields are declared with ``spec`` (checked key by key),
``dict`` (a free mapping the implementation checks itself, as highway-env's extra
config), or None (no parameters: a non-empty ``params`` is an error).

Entries are imported lazily: a scenario naming ``synthetic`` never imports highway-env.
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.metadata
import os
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from roco_env.schema import ConfigError, build, unknown_key_message

__all__ = ["KINDS", "SCENARIO_FIELDS", "StageEntry", "available_stages", "checked_params",
           "register_stage",
           "stage", "unregister_stage"]

# kind -> (scenario section, the field naming the implementation, the field of its params)
SCENARIO_FIELDS: dict[str, tuple[str, str, str]] = {
    "traffic": ("traffic", "source", "params"),
    "noise": ("noise", "model", "params"),
    "detector": ("detector", "preset", "params"),
    "fusion": ("fusion", "method", "params"),
    "reward": ("evaluation", "reward", "reward_params"),
    "delay": ("comm", "delay", "delay_params"),
    "loss": ("comm", "loss", "loss_params"),
    "attack": ("attack", "kind", "params"),
}
KINDS: tuple[str, ...] = tuple(SCENARIO_FIELDS)

_SENSING = "roco_env.sensing.detector"
_LEARNED_PARAMS = "roco_env.sensing.learned_params:LearnedDetectorParams"
_REWARDS = "roco_env.evaluation"
_DELAY = "roco_env.comm.delay"
_LOSS = "roco_env.comm.loss"

# kind -> name -> (factory target, params: a target, "dict" or None). Imported on first use.
_BUILT_IN: dict[str, dict[str, tuple[str, str | None]]] = {
    "traffic": {
        "synthetic": ("roco_env.traffic.synthetic:make_synthetic", None),
        "highway_env": ("roco_env.traffic.highway_env_source:HighwayEnvSource", "dict"),
        "opv2v": ("roco_env.traffic.replay:OPV2VReplay", None),
        "dair": ("roco_env.traffic.replay:DairReplay", None),
        "frames": ("roco_env.traffic.frames:frames_source", None),
    },
    "noise": {
        "gaussian": ("roco_env.noise:GaussianNoise.from_config", None),
        "laplace": ("roco_env.noise:LaplaceNoise.from_config", None),
        "bias": ("roco_env.noise:BiasNoise.from_config", None),
        "drift": ("roco_env.noise:DriftNoise.from_config", None),
        "ar1": ("roco_env.noise:AR1Noise.from_config", "roco_env.noise:AR1Params"),
        "localization": ("roco_env.noise:LocalizationNoise.from_config",
                         "roco_env.noise:LocalizationParams"),
    },
    "detector": {
        "ideal": (f"{_SENSING}:ideal_detector", f"{_SENSING}:DetectorParams"),
        "realistic": (f"{_SENSING}:realistic_detector", f"{_SENSING}:DetectorParams"),
        "learned": ("roco_env.sensing.learned:make_learned_detector", _LEARNED_PARAMS),
    },
    "fusion": {
        "late": ("roco_env.fusion.late:LateFusion", None),
        "intermediate": ("roco_env.fusion.intermediate:IntermediateFusion", None),
        "none": ("roco_env.fusion.late:NoFusion", None),
    },
    "reward": {
        **{name: (f"{_REWARDS}:APReward.from_config", None) for name in ("ap30", "ap50", "ap70")},
        **{f"{name}_gain": (f"{_REWARDS}:APGainReward.from_config", None)
           for name in ("ap30", "ap50", "ap70")},
        "neg_rpe": (f"{_REWARDS}:NegativeRPEReward.from_config", None),
    },
    "delay": {
        "none": (f"{_DELAY}:NoDelay.from_config", None),
        "fixed": (f"{_DELAY}:FixedDelay.from_config", f"{_DELAY}:FixedDelayParams"),
        "uniform": (f"{_DELAY}:UniformDelay.from_config", f"{_DELAY}:UniformDelayParams"),
        "opencood": (f"{_DELAY}:OpenCOODDelay.from_config", f"{_DELAY}:OpenCOODDelayParams"),
        "distance": (f"{_DELAY}:DistanceDelay.from_config", f"{_DELAY}:DistanceDelayParams"),
    },
    "loss": {
        "none": (f"{_LOSS}:NoLoss.from_config", None),
        "bernoulli": (f"{_LOSS}:BernoulliLoss.from_config", f"{_LOSS}:BernoulliLossParams"),
        "gilbert_elliott": (f"{_LOSS}:GilbertElliottLoss.from_config",
                            f"{_LOSS}:GilbertElliottParams"),
    },
    "attack": {
        "none": ("roco_env.attacks.attack_stage:NoAttack", None),
        "pose_spoof": ("roco_env.attacks.pose:PoseSpoof", "roco_env.attacks.pose:PoseSpoofParams"),
        "ghost": ("roco_env.attacks.ghost:Ghost", "roco_env.attacks.ghost:GhostParams"),
        "erase": ("roco_env.attacks.erase:Erase", "roco_env.attacks.erase:EraseParams"),
        "learned": ("roco_env.attacks.learned_attack:LearnedAttack",
                    "roco_env.attacks.learned_attack:LearnedAttackParams"),
    },
}

# names registered by register_stage in this process (kind -> name -> entry)
_REGISTERED: dict[str, dict[str, StageEntry]] = {kind: {} for kind in KINDS}


@dataclass(frozen=True)
class StageEntry:
    """One registered implementation: ``factory`` and ``params`` as callables/classes or
    import targets ``"module:attribute"`` (resolved on first use)."""

    kind: str
    name: str
    factory: Callable | str
    params: type | str | None = None

    def load_factory(self) -> Callable:
        """The factory, imported if given as a target."""
        return _resolve(self.factory, self) if isinstance(self.factory, str) else self.factory

    def params_class(self) -> type | None:
        """The parameter dataclass, ``dict`` (a free mapping) or None (no parameters)."""
        if self.params == "dict":
            return dict
        if isinstance(self.params, str):
            return _resolve(self.params, self)
        return self.params


def _resolve(target: str, entry: StageEntry) -> Any:
    """``"module:attr.attr"`` imported; a ConfigError naming the stage if it fails."""
    module_name, _, attributes = target.partition(":")
    try:
        value: Any = importlib.import_module(module_name)
        for attribute in attributes.split("."):
            value = getattr(value, attribute)
    except (ImportError, AttributeError) as exc:
        raise ConfigError(f"{entry.kind} {entry.name!r}: cannot load {target!r}: {exc}") from exc
    return value


# (sys.path when scanned, kind -> entry points found then): see _entry_points.
_SCANNED: tuple[tuple, dict[str, dict[str, StageEntry]]] | None = None


def _entry_points(kind: str) -> dict[str, StageEntry]:
    """Installed packages' stages of ``kind`` (group ``roco_env.<kind>``); scanned once
    per ``sys.path`` (a scan reads every installed distribution's metadata)."""
    global _SCANNED
    if _SCANNED is None or _SCANNED[0] != tuple(sys.path):
        found = {k: {ep.name: _entry_point_stage(k, ep)
                     for ep in importlib.metadata.entry_points(group=f"roco_env.{k}")}
                 for k in KINDS}
        _SCANNED = (tuple(sys.path), found)
    return _SCANNED[1][kind]


def _entry_point_stage(kind: str, point: importlib.metadata.EntryPoint) -> StageEntry:
    """An entry point's stage; its parameters are the factory's ``PARAMS`` attribute."""
    return _LazyParamsEntry(kind, point.name, point.value)


class _LazyParamsEntry(StageEntry):
    """An entry whose parameter class is the loaded factory's ``PARAMS`` attribute."""

    def params_class(self) -> type | None:
        return getattr(self.load_factory(), "PARAMS", None)


def _entries(kind: str) -> dict[str, StageEntry]:
    if kind not in KINDS:
        raise ConfigError(f"unknown stage kind {kind!r}; allowed: {', '.join(KINDS)}")
    built_in = {name: StageEntry(kind, name, factory, params)
                for name, (factory, params) in _BUILT_IN[kind].items()}
    return {**_entry_points(kind), **_REGISTERED[kind], **built_in}


def available_stages(kind: str) -> tuple[str, ...]:
    """The names a scenario may give for stage ``kind``: built-in first, then registered
    ones and installed packages' (sorted)."""
    entries = _entries(kind)
    return tuple(_BUILT_IN[kind]) + tuple(sorted(set(entries) - set(_BUILT_IN[kind])))


def stage(kind: str, name: str) -> StageEntry:
    """The entry registered as ``name`` for ``kind``; a ConfigError naming the scenario
    field and the allowed names otherwise."""
    entries = _entries(kind)
    if name not in entries:
        section, field, _ = SCENARIO_FIELDS[kind]
        raise ConfigError(f"{section}.{field}={name!r} is not allowed; choose one of "
                          f"{list(available_stages(kind))} (or register your own with "
                          f"roco_env.register_stage({kind!r}, name, factory))")
    return entries[name]


def checked_params(kind: str, name: str, given: Any, where: str,
                   base: str | os.PathLike | None = None) -> dict:
    """The parameters ``given`` (a mapping) to stage ``kind`` ``name``, checked against its
    parameter dataclass: the keys given, their values checked (relative ``path`` fields
    joined to ``base``); a free mapping (``dict``) is returned as is. A ConfigError
    names ``where``, the scenario key and the allowed values; a key that belongs to
    another implementation of the kind says which."""
    section, field, params_field = SCENARIO_FIELDS[kind]
    prefix = f"{section}.{params_field}."
    params = stage(kind, name).params_class()
    if not isinstance(given, Mapping):
        raise ConfigError(f"{where}: {section}.{params_field} must be a mapping of keys; got "
                          f"{type(given).__name__} ({given!r})")
    if params is dict:
        return dict(given)
    names = [] if params is None else [f.name for f in dataclasses.fields(params)]
    unknown = sorted(set(given) - set(names), key=str)
    if unknown:
        message = unknown_key_message(where, prefix + str(unknown[0]),
                                      [prefix + key for key in names])
        owners = [other for other in available_stages(kind) if _takes(kind, other, unknown[0])]
        if owners:
            message += (f"; {prefix}{unknown[0]} is a parameter of {section}.{field} "
                        f"{' / '.join(map(repr, owners))}, not of {name!r}")
        raise ConfigError(message)
    if params is None:
        return {}
    checked = build(params, given, where, prefix, base)
    return {key: getattr(checked, key) for key in given}


def _takes(kind: str, name: str, key: str) -> bool:
    """Whether stage ``kind`` ``name`` declares a parameter ``key``."""
    params = stage(kind, name).params_class()
    return dataclasses.is_dataclass(params) and key in {f.name for f in dataclasses.fields(params)}


def register_stage(kind: str, name: str, factory: Callable | str,
                   params: type | None = None) -> None:
    """Make ``factory`` selectable as ``name`` for stage ``kind`` (see the module
    docstring for what each kind's factory receives). ``params``: the dataclass of its
    parameters (fields declared with ``roco_env.schema.spec``), ``dict`` for a free
    mapping, None for none. A built-in name cannot be replaced."""
    _entries(kind)  # checks the kind
    if not isinstance(name, str) or not name.isidentifier():
        raise ConfigError(f"register_stage: name must be an identifier; got {name!r}")
    if name in _BUILT_IN[kind]:
        raise ConfigError(f"register_stage: {kind} {name!r} is built in; choose another name")
    if not (callable(factory) or isinstance(factory, str) and ":" in factory):
        raise ConfigError(f"register_stage: factory must be callable or an import target "
                          f"'module:attribute'; got {factory!r}")
    if not (params is None or params is dict or isinstance(params, type)):
        raise ConfigError(f"register_stage: params must be a dataclass, dict or None; "
                          f"got {params!r}")
    _REGISTERED[kind][name] = StageEntry(kind, name, factory, params)


def unregister_stage(kind: str, name: str) -> None:
    """Forget a name :func:`register_stage` added (built-in names stay)."""
    _REGISTERED[kind].pop(name, None)
