"""Detector model: turns visibility into each agent's boxes, scores and uncertainties.

One parametric model; presets are parameter sets (``DetectorConfig.params``
override preset values). Per agent, for every visible object (fraction above
``min_fraction``):

* detected with probability ``p_max / (1 + (returns_50 / returns) ** returns_slope)``;
* box = exact box in the agent's TRUE sensor frame plus noise (when ``noisy``):
  centre x and y each ~ N(0, sigma_xy), yaw ~ N(0, sigma_yaw) with
  ``sigma_xy = sigma_xy + sigma_xy_per_m * distance + sigma_xy_occlusion * (1 - fraction)``
  and the same form for ``sigma_yaw`` (metres, radians, distance in metres);
  sizes multiplied by ``exp(N(0, sigma_size + sigma_size_occlusion * (1 - fraction)))``;
  heading flipped by pi with probability ``flip_prob``; z is kept (BEV model);
* uncertainty = (sigma_xy, sigma_xy, sigma_yaw) * ``calibration`` (1.0 = honest:
  exactly the std used to draw the centre/yaw noise; for ``ideal`` the nominal
  std of an unperturbed box);
* score = ``score_floor + (1 - score_floor) * q`` plus N(0, score_noise), clipped
  to [0.01, 1], where q = returns / (returns + returns_50) (q = 1 when noise-free);
* clutter: Poisson(``fp_rate``) false positives per agent and frame, car-sized
  boxes uniform over the sensor disk, scores ~ U(0.01, ``fp_score_max``),
  uncertainty from the far-range sigma; object id -1.

Draw order per agent is fixed, so the same generator state gives the same output.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol

import numpy as np

from roco_env.geometry import se2_inverse, transform_boxes, wrap_angle
from roco_env.scenario import DetectorConfig
from roco_env.schema import build, spec
from roco_env.sensing.visibility import Visibility
from roco_env.stages import checked_params, stage
from roco_env.traffic.state import WorldState

__all__ = ["FP_SIZE_MEAN", "PRESETS", "AgentDetections", "Detector", "DetectorParams",
           "Perception", "PerceptionModel", "make_detector"]


@dataclass
class DetectorParams:
    """The detector model's parameters (roco_env.sensing.detector): the defaults are
    the ``realistic`` preset; metres, radians, probabilities."""

    noisy: bool = spec(True, doc="perturb boxes, scores and sizes")
    min_fraction: float = spec(0.0, low=0.0, high=1.0, doc="visible fraction needed")
    p_max: float = spec(0.97, low=0.0, high=1.0, doc="detection probability, many returns")
    returns_50: float = spec(12.0, low=0.0, doc="LiDAR returns at half p_max")
    returns_slope: float = spec(1.5, low=0.0, high=20.0, low_open=True)
    sigma_xy: float = spec(0.06, low=0.0, high=10.0, low_open=True, doc="centre std, m")
    sigma_xy_per_m: float = spec(0.002, low=0.0, high=1.0, doc="centre std growth, m per m")
    sigma_xy_occlusion: float = spec(0.25, low=0.0, high=10.0, doc="m at full occlusion")
    sigma_yaw: float = spec(0.02, low=0.0, high=3.141592653589793, low_open=True,
                            doc="yaw std, rad")
    sigma_yaw_per_m: float = spec(0.0004, low=0.0, high=0.1, doc="yaw std growth, rad per m")
    sigma_yaw_occlusion: float = spec(0.1, low=0.0, high=3.141592653589793,
                                      doc="rad at full occlusion")
    sigma_size: float = spec(0.03, low=0.0, high=1.0, doc="log-size std")
    sigma_size_occlusion: float = spec(0.05, low=0.0, high=1.0)
    flip_prob: float = spec(0.03, low=0.0, high=1.0, doc="probability of a heading flip")
    fp_rate: float = spec(1.0, low=0.0, high=1000.0, doc="false positives per frame")
    fp_score_max: float = spec(0.45, low=0.01, high=1.0, low_open=True)
    score_floor: float = spec(0.4, low=0.0, high=1.0)
    score_noise: float = spec(0.05, low=0.0, high=1.0)
    calibration: float = spec(1.0, low=0.0, high=100.0, low_open=True,
                              doc="reported / true uncertainty")


# The realistic preset is DetectorParams' defaults.
_REALISTIC: dict[str, Any] = dataclasses.asdict(DetectorParams())

PRESETS: dict[str, dict[str, Any]] = {
    "ideal": {
        **_REALISTIC,
        "noisy": False,
        "p_max": 1.0,
        "returns_50": 0.0,
        "sigma_xy": 0.05,
        "sigma_xy_per_m": 0.0,
        "sigma_xy_occlusion": 0.0,
        "sigma_yaw": 0.01,
        "sigma_yaw_per_m": 0.0,
        "sigma_yaw_occlusion": 0.0,
        "flip_prob": 0.0,
        "fp_rate": 0.0,
        "score_noise": 0.0,
    },
    "realistic": dict(_REALISTIC),
}

# Car-sized clutter boxes: (mean, std) of l, w, h in metres (the mean also sizes an
# attack's ghost cars, roco_env.attacks.ghost).
FP_SIZE_MEAN = np.array([4.5, 1.9, 1.6])
_FP_SIZE_STD = np.array([0.4, 0.15, 0.15])


@dataclass(frozen=True)
class AgentDetections:
    """One agent's detections in its TRUE sensor frame (K boxes).

    boxes (K, 7) (x, y, z, l, w, h, yaw); uncertainty (K, 3) (sigma_x m,
    sigma_y m, sigma_yaw rad); scores (K,) in (0, 1]; object_ids (K,) int64 true
    object id or -1 for a false positive (ground truth: never put in a message).
    """

    boxes: np.ndarray
    uncertainty: np.ndarray
    scores: np.ndarray
    object_ids: np.ndarray

    @classmethod
    def empty(cls) -> AgentDetections:
        """No detections (K = 0)."""
        return cls(np.zeros((0, 7)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int64))


class Perception(NamedTuple):
    """What a detector makes of one step: per agent its detections (true sensor frame,
    in ``state.agent_ids`` order), and the encoder maps intermediate fusion warps and
    decodes (a learned detector's :class:`~roco_env.sensing.learned.model.EncoderMaps`;
    None for detectors without feature maps)."""

    detections: list[AgentDetections]
    encoder_maps: Any = None


class PerceptionModel(Protocol):
    """The detector stage (roco_env.stages, kind ``detector``): its factory is called
    with the scenario's checked ``detector.params`` (the keys given) and the evaluation
    region ``(x_range, y_range)`` (m, agent frame) or None."""

    #: True when headings are only known up to a half turn (the env then exchanges them
    #: in one convention, roco_env.geometry.canonical_axial_yaw).
    axial_headings: bool

    def perceive(self, state: WorldState, visibility: Visibility,
                 rng: np.random.Generator) -> Perception:
        """Every agent's detections of ``state``; draws only from ``rng``."""


class Detector:
    """The detector model of the module docstring with fixed, validated parameters."""

    #: Headings are the objects' true headings plus noise (the presets' ``flip_prob``
    #: turns a few by pi, as real detectors' direction classifiers err): not declared
    #: up to pi, as a learned detector that cannot tell front from back declares them.
    axial_headings = False

    def __init__(self, params: dict[str, Any]) -> None:
        """params: any subset of the parameter names; the rest take `realistic` defaults."""
        self.params: dict[str, Any] = dataclasses.asdict(
            build(DetectorParams, params, where="detector", prefix="detector.params."))

    def sigmas(self, distance: np.ndarray, fraction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Std of the centre (m, per axis) and yaw (rad) noise at distance (m), visible fraction."""
        p = self.params
        occl = 1.0 - np.clip(fraction, 0.0, 1.0)
        sigma_xy = p["sigma_xy"] + p["sigma_xy_per_m"] * distance + p["sigma_xy_occlusion"] * occl
        sigma_yaw = (p["sigma_yaw"] + p["sigma_yaw_per_m"] * distance
                     + p["sigma_yaw_occlusion"] * occl)
        return sigma_xy, sigma_yaw

    def detection_probability(self, returns: np.ndarray) -> np.ndarray:
        """Probability of detecting an object with ``returns`` expected LiDAR points."""
        p = self.params
        returns = np.asarray(returns, dtype=float)
        if p["returns_50"] == 0.0:
            return np.full(returns.shape, p["p_max"])
        ratio = np.divide(p["returns_50"], returns, out=np.full(returns.shape, np.inf),
                          where=returns > 0.0)
        return p["p_max"] / (1.0 + ratio ** p["returns_slope"])

    def perceive(self, state: WorldState, visibility: Visibility,
                 rng: np.random.Generator) -> Perception:
        """The detections of :meth:`detect` and no encoder maps."""
        return Perception(self.detect(state, visibility, rng))

    def detect(self, state: WorldState, visibility: Visibility,
               rng: np.random.Generator) -> list[AgentDetections]:
        """One :class:`AgentDetections` per agent, in ``state.agent_ids`` order."""
        boxes_world = np.asarray(state.object_boxes, dtype=float).reshape(-1, 7)
        return [
            self._detect_agent(state, visibility, a, boxes_world, rng)
            for a in range(state.num_agents)
        ]

    def _detect_agent(self, state: WorldState, visibility: Visibility, a: int,
                      boxes_world: np.ndarray, rng: np.random.Generator) -> AgentDetections:
        p = self.params
        cand = np.flatnonzero(visibility.visible[a] & (visibility.fraction[a] > p["min_fraction"]))
        returns = visibility.returns[a, cand]
        detected = rng.random(cand.size) < self.detection_probability(returns)
        cand, returns = cand[detected], returns[detected]
        fraction = visibility.fraction[a, cand]
        boxes = transform_boxes(boxes_world[cand], se2_inverse(state.agent_poses[a]))
        sigma_xy, sigma_yaw = self.sigmas(np.hypot(boxes[:, 0], boxes[:, 1]), fraction)
        if p["noisy"]:
            boxes = self._perturb(boxes, sigma_xy, sigma_yaw, fraction, rng)
            quality = returns / (returns + max(p["returns_50"], 1e-9))
            scores = p["score_floor"] + (1.0 - p["score_floor"]) * quality
            scores = scores + p["score_noise"] * rng.standard_normal(cand.size)
        else:
            scores = np.ones(cand.size)
        unc = p["calibration"] * np.stack([sigma_xy, sigma_xy, sigma_yaw], axis=1)
        fp = self._clutter(float(state.sensor_ranges[a]), float(state.ground_heights[a]), rng)
        return AgentDetections(
            boxes=np.concatenate([boxes, fp.boxes]),
            uncertainty=np.concatenate([unc, fp.uncertainty]),
            scores=np.concatenate([np.clip(scores, 0.01, 1.0), fp.scores]),
            object_ids=np.concatenate([state.object_ids[cand].astype(np.int64), fp.object_ids]),
        )

    def _perturb(self, boxes: np.ndarray, sigma_xy: np.ndarray, sigma_yaw: np.ndarray,
                 fraction: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        p = self.params
        n = boxes.shape[0]
        out = boxes.copy()
        out[:, :2] += sigma_xy[:, None] * rng.standard_normal((n, 2))
        sigma_size = p["sigma_size"] + p["sigma_size_occlusion"] * (1.0 - fraction)
        out[:, 3:6] *= np.exp(sigma_size[:, None] * rng.standard_normal((n, 3)))
        flips = rng.random(n) < p["flip_prob"]
        out[:, 6] = wrap_angle(out[:, 6] + sigma_yaw * rng.standard_normal(n) + np.pi * flips)
        return out

    def _clutter(self, sensor_range: float, ground: float,
                 rng: np.random.Generator) -> AgentDetections:
        """Poisson false positives: car-sized boxes uniform over the sensor disk, standing
        on the ground under the agent (world z ``ground``, m)."""
        p = self.params
        n = int(rng.poisson(p["fp_rate"]))
        if n == 0:
            return AgentDetections.empty()
        radius = sensor_range * np.sqrt(rng.random(n))
        bearing = rng.uniform(-np.pi, np.pi, n)
        size = np.maximum(FP_SIZE_MEAN + _FP_SIZE_STD * rng.standard_normal((n, 3)), 0.5)
        yaw = rng.uniform(-np.pi, np.pi, n)
        boxes = np.column_stack([radius * np.cos(bearing), radius * np.sin(bearing),
                                 ground + 0.5 * size[:, 2], size, yaw])
        sigma_xy, sigma_yaw = self.sigmas(np.full(n, sensor_range), np.zeros(n))
        unc = p["calibration"] * np.stack([sigma_xy, sigma_xy, sigma_yaw], axis=1)
        scores = rng.uniform(0.01, p["fp_score_max"], n)
        return AgentDetections(boxes, unc, scores, np.full(n, -1, dtype=np.int64))


def ideal_detector(params: dict[str, Any], region: Any = None) -> Detector:
    """The ``ideal`` preset with ``params`` overriding it (stage factory)."""
    return Detector({**PRESETS["ideal"], **params})


def realistic_detector(params: dict[str, Any], region: Any = None) -> Detector:
    """The ``realistic`` preset with ``params`` overriding it (stage factory)."""
    return Detector({**PRESETS["realistic"], **params})


def make_detector(config: DetectorConfig,
                  region: tuple[Sequence[float], Sequence[float]] | None = None
                  ) -> PerceptionModel:
    """Build the detector stage ``config.preset`` names with ``config.params``.

    ``learned`` builds :class:`roco_env.sensing.learned.LearnedDetector` (loads torch
    and the weights; params: weights, device, score_threshold, threads), reading each
    agent's sensor range within ``region`` ((x_range, y_range), m, agent frame: the
    evaluation range; None: the grid it was trained on).
    Raises a ConfigError (a ValueError) naming the preset or parameter and the allowed
    values.
    """
    params = checked_params("detector", config.preset, config.params, where="detector")
    return stage("detector", config.preset).load_factory()(params, region)
