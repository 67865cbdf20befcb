"""Sensing: what each agent sees and detects, its BEV features and its messages.

Pipeline per step: ``compute_visibility(state)`` (range, 2.5D ray-cast
occlusion, expected LiDAR returns) -> ``make_detector(config).detect(state,
visibility, rng)`` (boxes, uncertainties, scores in each agent's true frame) ->
optional ``bev_features(visibility, agent, grid)`` -> ``build_messages(...)``
(what collaborators send an ego). See docs/architecture.md, step 5.
"""

import importlib
from typing import Any

from roco_env.sensing.bev_grid import BevGrid
from roco_env.sensing.detector import PRESETS, AgentDetections, Detector, make_detector
from roco_env.sensing.messages import Message, build_messages, select_collaborators
from roco_env.sensing.visibility import LidarModel, RayHits, Visibility, compute_visibility

__all__ = [
    "CHANNELS",
    "PRESETS",
    "AgentDetections",
    "BevGrid",
    "Detector",
    "LidarModel",
    "Message",
    "RayHits",
    "Visibility",
    "bev_features",
    "build_messages",
    "compute_visibility",
    "make_detector",
    "select_collaborators",
    "warp_bev",
]

# BEV features need torch: loaded on first use, so an env without features never imports it.
_FEATURES = ("CHANNELS", "bev_features", "warp_bev")


def __getattr__(name: str) -> Any:
    if name in _FEATURES:
        return getattr(importlib.import_module("roco_env.sensing.features"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
