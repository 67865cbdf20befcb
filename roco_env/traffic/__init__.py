"""Where objects and agents are, step by step (docs/architecture.md).

``make_traffic_source(config)`` builds the source named by ``config.traffic.source``:

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
from collections.abc import Sequence
from typing import Any

from roco_env.scenario import ScenarioConfig
from roco_env.traffic.state import AGENT_KINDS, OBJECT_CLASSES, TrafficSource, WorldState

_LAZY = {
    "LaneTraffic": "roco_env.traffic.synthetic",
    "ParkingLotTraffic": "roco_env.traffic.synthetic",
    "HighwayEnvSource": "roco_env.traffic.highway_env_source",
    "OPV2VReplay": "roco_env.traffic.replay",
    "DairReplay": "roco_env.traffic.replay",
    "FramesSource": "roco_env.traffic.frames",
    "Frame": "roco_env.traffic.frames",
    "export_opv2v": "roco_env.traffic.export",
}

__all__ = ["make_traffic_source", "WorldState", "TrafficSource", "OBJECT_CLASSES",
           "AGENT_KINDS", *_LAZY]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def make_traffic_source(config: ScenarioConfig, frames: Sequence[Any] | None = None
                        ) -> TrafficSource:
    """Build the traffic source of ``config.traffic.source``.

    ``frames`` (a sequence of :class:`roco_env.traffic.frames.Frame`) is required
    for source ``frames`` and rejected otherwise.
    """
    source = config.traffic.source
    if frames is not None and source != "frames":
        raise ValueError(f"frames= is only used with traffic.source='frames', not {source!r}")
    if source == "synthetic":
        from roco_env.traffic.synthetic import make_synthetic

        return make_synthetic(config)
    if source == "highway_env":
        from roco_env.traffic.highway_env_source import HighwayEnvSource

        return HighwayEnvSource(config)
    if source in ("opv2v", "dair"):
        from roco_env.traffic.replay import DairReplay, OPV2VReplay

        return (OPV2VReplay if source == "opv2v" else DairReplay)(config)
    if source == "frames":
        if frames is None:
            raise ValueError(
                "traffic.source='frames' needs your frames: pass frames=[Frame(...), ...] to "
                "roco_env.parallel_env / roco_env.env (or to make_traffic_source)"
            )
        from roco_env.traffic.frames import FramesSource

        return FramesSource(frames, config.agents, config.traffic.dt)
    raise ValueError(
        f"traffic.source={source!r} is unknown; allowed: synthetic, highway_env, opv2v, dair, frames"
    )
