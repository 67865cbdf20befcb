"""Fusion of an ego's own outputs with its collaborators' (docs/architecture.md, step 3).

The fusion stage (:class:`~roco_env.fusion.stage.Fusion`, built by :func:`make_fusion`
from ``fusion.method``): ``late`` merges boxes (the default; ``merge_many`` and
``suppress`` merge and NMS many egos at once); ``intermediate``
(:mod:`roco_env.fusion.intermediate`, imported on demand: it needs torch) warps, gates
and max-fuses BEV feature maps; ``none`` keeps the ego's own boxes.
"""

from typing import Any

from roco_env.fusion.late import (
    EGO_SOURCE,
    FusedDetections,
    late_fusion,
    merge_into_ego_frame,
    merge_many,
    own_detections,
    suppress,
)
from roco_env.fusion.stage import Fusion
from roco_env.scenario import ScenarioConfig
from roco_env.stages import stage

__all__ = ["EGO_SOURCE", "FusedDetections", "Fusion", "late_fusion", "make_fusion",
           "merge_into_ego_frame", "merge_many", "own_detections", "suppress"]


def make_fusion(config: ScenarioConfig, detector: Any) -> Fusion:
    """The fusion stage ``config.fusion.method`` names (roco_env.stages), for the
    scenario's ``detector`` stage."""
    return stage("fusion", config.fusion.method).load_factory()(config, detector)
