"""Sensing: what each agent sees and detects, its BEV features and its messages.

Pipeline per step: ``compute_visibility(state)`` (range, 2.5D ray-cast
occlusion, expected LiDAR returns) -> ``make_detector(config).detect(state,
visibility, rng)`` (boxes, uncertainties, scores in each agent's true frame) ->
optional ``bev_features(visibility, agent, grid)`` -> ``build_messages(...)``
(what collaborators send an ego). See DESIGN.md section 5.
"""

from roco_env.sensing.detector import PRESETS, AgentDetections, Detector, make_detector
from roco_env.sensing.features import CHANNELS, BevGrid, bev_features, warp_bev
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
