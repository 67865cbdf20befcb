"""The fusion stage's interface (roco_env.stages, kind ``fusion``).

A fusion method merges each evaluated ego's own outputs with those of the
collaborators it keeps, moved by the corrected relative poses; the environment then
drops boxes on the ego's own footprint and runs the NMS every method shares
(``fusion.nms_iou``). Its factory is called as ``factory(config, detector)`` with the
scenario (:class:`~roco_env.scenario.ScenarioConfig`; a registered method reads its
``fusion.params`` there) and the detector stage (whose encoder maps intermediate
fusion decodes).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol

import numpy as np

from roco_env.fusion.late import FusedDetections
from roco_env.traffic.state import WorldState

__all__ = ["Fusion", "FusionFrame"]


class FusionFrame(Protocol):
    """What a step offers fusion (a :class:`roco_env.pipeline.PerceptionFrame`):
    the world, every agent's view (its own boxes and scores, its collaborators' as
    received, in their true sensor frames) and the detector's encoder maps (or None)."""

    state: WorldState
    views: Sequence[Any]
    encoder_maps: Any


class Fusion(Protocol):
    """A fusion method."""

    def fuse(self, frame: FusionFrame, egos: Sequence[int], kept: Sequence[np.ndarray],
             poses: Sequence[np.ndarray]) -> list[FusedDetections]:
        """Every ego's merged detections before NMS, in its true sensor frame.

        egos: agent indices; kept[k]: a boolean mask over ego k's collaborator slots
        (rejected collaborators are False); poses[k]: (sum(kept[k]), 3) corrected
        relative poses T_{j->i} (x m, y m, yaw rad) of the kept slots, in slot order.
        """

