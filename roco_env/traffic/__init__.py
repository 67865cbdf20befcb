"""Where objects and agents are, step by step (docs/architecture.md).

``make_traffic_source(config)`` builds the source named by ``config.traffic.source``
(a stage, roco_env.stages; built in):

- ``synthetic``: numpy IDM traffic on a layout (:mod:`.synthetic`, :mod:`.layouts`).
- ``highway_env``: highway-env scenes run headless (:mod:`.highway_env_source`).
- ``opv2v`` / ``dair``: dataset label replay from ``traffic.path`` (:mod:`.replay`).
- ``frames``: the user's own per-step arrays (:class:`.frames.FramesSource`), passed
  as ``make_traffic_source(config, frames=...)``.

Every source returns :class:`WorldState` snapshots with a constant agent set.
Heavy sources (highway-env) are imported only when used.
"""

from __future__ import annotations

import importlib
import inspect
from collections.abc import Sequence
from typing import Any

from roco_env.scenario import ScenarioConfig
from roco_env.stages import stage
from roco_env.traffic.state import AGENT_KINDS, OBJECT_CLASSES, TrafficSource, WorldState

_LAZY = {
    "LaneTraffic": "roco_env.traffic.synthetic",
    "ParkingLotTraffic": "roco_env.traffic.synthetic",
    "HighwayEnvSource": "roco_env.traffic.highway_env_source",
    "OPV2VReplay": "roco_env.traffic.replay",
    "DairReplay": "roco_env.traffic.replay",
    "FramesSource": "roco_env.traffic.frames",
    "Frame": "roco_env.traffic.frames",
    "export_opv2v": "roco_env.traffic.opv2v_export",
}

__all__ = ["make_traffic_source", "WorldState", "TrafficSource", "OBJECT_CLASSES",
           "AGENT_KINDS", *_LAZY]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def make_traffic_source(config: ScenarioConfig, frames: Sequence[Any] | None = None
                        ) -> TrafficSource:
    """Build the traffic stage ``config.traffic.source`` names (roco_env.stages).

    ``frames`` (a sequence of :class:`roco_env.traffic.frames.Frame`) is passed to a
    source whose factory takes them (``frames``, which requires them) and rejected by
    the others.
    """
    source = config.traffic.source
    factory = stage("traffic", source).load_factory()
    if frames is None:
        return factory(config)
    if "frames" not in inspect.signature(factory).parameters:
        raise ValueError(f"frames= is only used with traffic.source='frames' (or a source "
                         f"whose factory takes frames), not {source!r}")
    return factory(config, frames=frames)
