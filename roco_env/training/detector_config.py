"""The settings of ``roco-env train-detector``: :class:`TrainConfig`, the one place of
their defaults, allowed values and help, and the command line's options (:data:`FLAGS`,
generated from it).

Torch-free, so that building the ``roco-env`` parser (every command's) never imports
torch; the training itself is :mod:`roco_env.training.train`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from roco_env.flags import SpecFlags
from roco_env.schema import ConfigError, check_fields, spec
from roco_env.sensing.bev_grid import BevGrid
from roco_env.sensing.learned_params import FUSIONS
from roco_env.sensing.lidar import ScanNoise
from roco_env.training.data import TRAIN_SCENARIOS

__all__ = ["FLAGS", "WHERE", "TrainConfig"]

# Where the errors of a training configuration say they come from.
WHERE = "train-detector"


@dataclass(frozen=True)
class TrainConfig:
    """Everything that determines a training run (recorded in the weights and report).

    Every value is checked as it is constructed, directly (``TrainConfig(lr=1e-3)``) or
    from a mapping by :func:`~roco_env.schema.build` (``build(TrainConfig, values,
    WHERE)``); the fields' docs are the help of the options of ``roco-env train-detector``
    (:data:`FLAGS`). ``noise``: the scan noise of the training scenes.
    """

    x_range: tuple[float, float] = spec((-70.4, 70.4), doc="detector raster extent along x, m")
    y_range: tuple[float, float] = spec((-40.0, 40.0), doc="detector raster extent along y, m")
    resolution: float = spec(0.8, low=0.0, low_open=True, doc="detector raster cell, m")
    widths: tuple[int, int, int] = spec((32, 64, 48), doc="network widths W1 W2 C")
    train_scenes: int = spec(800, low=1, doc="training scenes")
    val_scenes: int = spec(20, low=0, doc="validation scenes (0: none)")
    scenarios: tuple[str, ...] = spec(TRAIN_SCENARIOS, doc="training scenarios")
    val_scenarios: tuple[str, ...] = spec(("urban_intersection",),
                                          doc="validation scenarios")
    steps: int = spec(1200, low=1, doc="optimiser steps")
    scenes_per_step: int = spec(4, low=1, doc="scenes per batch")
    lr: float = spec(3e-3, low=0.0, low_open=True, doc="peak learning rate")
    pose_sigma_t: float = spec(0.2, low=0.0, doc="pose noise of the fused loss, translation "
                               "std in m (the RoCo paper's training protocol)")
    pose_sigma_r: float = spec(0.2, low=0.0, doc="pose noise of the fused loss, rotation std "
                               "in degrees")
    fused_x_range: tuple[float, float] | None = spec(
        None, doc="ego-frame x extent LOW HIGH (m) the fused loss decodes: the detector grid "
        "grown to cover it in whole feature cells, e.g. the evaluation range -140.8 140.8 "
        "(none: the detector grid)")
    fused_y_range: tuple[float, float] | None = spec(None, doc="the same along y")
    init: str | None = spec(None, path=True, doc="weights file to start from; its widths "
                            "must be --widths (none: random initialisation; --lr applies as "
                            "given)")
    train_encoder: bool = spec(True, doc="train the encoder; --no-train-encoder (or "
                               "--freeze-encoder) trains the trunk and heads only (needs "
                               "--init): a fine-tuning stage that keeps every encoder map")
    fusion: str = spec("max", choices=FUSIONS, doc="intermediate fusion of the fused loss "
                       "and of the weights: the maximum, or the maximum after a learned "
                       "per-cell gate on each collaborator's map")
    train_detector: bool = spec(True, doc="train the detector; --no-train-detector (or "
                                "--freeze-detector) trains the fusion gate only (needs --init "
                                "and --fusion gated): every detection of the start weights "
                                "stays as it was")
    warp_augment: float = spec(0.0, low=0.0, high=1.0, doc="share of single-agent maps "
                               "decoded after a random rigid warp (any heading, a shift of up "
                               "to one feature cell), so the network learns maps that survive "
                               "the warp of fusion")
    seed: int = spec(0, low=0, doc="training seed")
    threads: int = spec(2, low=1, doc="torch CPU threads")
    workers: int = spec(0, low=0, doc="processes generating scenes and batches (0: none; the "
                        "weights do not depend on it)")
    device: str = spec("cpu", choices=("cpu", "cuda"), doc="torch device")
    noise: ScanNoise = field(default_factory=ScanNoise)

    def __post_init__(self) -> None:
        """Every field's spec (:func:`~roco_env.schema.check_fields`), then the rules one
        field's spec cannot state: the fused ranges' values, and the fields that go
        together."""
        check_fields(self, WHERE)
        for name in ("fused_x_range", "fused_y_range"):
            value = getattr(self, name)
            if value is not None and not (len(value) == 2 and all(map(math.isfinite, value))
                                          and value[0] < value[1]):
                option = "--" + name.replace("_", "-")
                raise ConfigError(f"{WHERE}: {name} must be None or two finite numbers (low, "
                                  f"high) with low < high, in m ({option} LOW HIGH); got "
                                  f"{value!r}")
        if not self.train_encoder and self.init is None:
            raise ConfigError(f"{WHERE}: train_encoder=False (a frozen encoder, "
                              "--freeze-encoder) needs init, the weights file to start from "
                              "(--init FILE)")
        if not self.train_detector and (self.init is None or self.fusion != "gated"):
            raise ConfigError(f"{WHERE}: train_detector=False (a frozen detector, "
                              "--freeze-detector) trains the fusion gate alone: it needs "
                              "init, the weights file to start from (--init FILE), and "
                              "fusion='gated' (--fusion gated)")

    @property
    def trains_encoder(self) -> bool:
        """Whether the encoder learns (not with a frozen encoder or detector)."""
        return self.train_encoder and self.train_detector

    @property
    def grid(self) -> BevGrid:
        return BevGrid(self.x_range, self.y_range, self.resolution)


# The command line's options (roco-env train-detector), one per field; ``--freeze-encoder``
# / ``--freeze-detector`` are the older names of ``--no-train-encoder`` /
# ``--no-train-detector``.
FLAGS = SpecFlags(TrainConfig, WHERE, aliases={"--freeze-encoder": ("train_encoder", False),
                                               "--freeze-detector": ("train_detector", False)})
