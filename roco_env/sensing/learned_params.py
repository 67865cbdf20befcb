"""The learned detector's parameters, declared apart from the detector so that checking a
scenario's ``detector.params`` never imports torch (roco_env.sensing.learned does)."""

from __future__ import annotations

from dataclasses import dataclass

from roco_env.schema import spec

__all__ = ["FUSIONS", "LearnedDetectorParams"]

# Intermediate fusion of the maps: the element-wise maximum, or the maximum after a learned
# per-cell weight on each collaborator's map (roco_env.sensing.learned.network.FusionGate).
FUSIONS = ("max", "gated")


@dataclass
class LearnedDetectorParams:
    """The learned detector's parameters (roco_env.sensing.learned)."""

    weights: str | None = spec(None, path=True,
                               doc="weights file; None = the shipped weights")
    device: str = spec("cpu", choices=("cpu", "cuda"), doc="torch device")
    score_threshold: float = spec(0.2, low=0.0, high=1.0, low_open=True, high_open=True,
                                  doc="decoded boxes below this score are dropped")
    threads: int = spec(1, low=1, high=256,
                        doc="CPU threads of the network (torch, set process-wide when the "
                        "detector is built) and of intermediate fusion")
    gate: bool | None = spec(None, doc="intermediate fusion through the weights' learned "
                             "fusion gate: None = when they hold one, true = they must, false "
                             "= the plain maximum")
    box_sigma_xy: float = spec(0.0, low=0.0, high=10.0,
                               doc="extra centre std (m, each axis) of the boxes each agent "
                               "reports and shares; its feature maps are untouched")
    box_sigma_yaw: float = spec(0.0, low=0.0, high=3.141592653589793,
                                doc="extra heading std (rad) of those boxes")
