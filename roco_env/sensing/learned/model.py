"""The learned detector at run time: weights loading, batched inference, box decoding.

A weights file (written by ``roco-env train-detector``, read with
``torch.load(weights_only=True)``: never unpickled) holds the network's
``state_dict`` and its metadata: the network shape (:class:`NetConfig`), the
detector grid (x_range, y_range, resolution of the LiDAR raster, agent frame),
the raster channel names (:data:`LIDAR_CHANNELS`), the scan noise it was
trained with and the training command. Every field is checked on load; a
missing, corrupt or mismatched file, or one with a NaN or infinite weight, raises
ValueError naming the problem.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
from collections.abc import Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment

from roco_env.geometry import se2_inverse, transform_boxes
from roco_env.schema import build
from roco_env.sensing.detector import AgentDetections, Perception
from roco_env.sensing.features import BevGrid, placement
from roco_env.sensing.learned.network import BevDetectorNet, NetConfig
from roco_env.sensing.learned.targets import SCORE_THRESHOLD, Decoded, decode, feature_grid
from roco_env.sensing.learned_params import LearnedDetectorParams
from roco_env.sensing.lidar import (
    LIDAR_CHANNELS,
    ScanNoise,
    ground_references,
    lidar_rasters,
    sample_scans,
)
from roco_env.sensing.visibility import Visibility
from roco_env.traffic.state import WorldState

__all__ = ["SHIPPED_WEIGHTS", "WEIGHTS_FILE", "EncoderMaps", "LearnedDetector", "load_checkpoint",
           "make_learned_detector", "save_checkpoint", "shipped_weights_path", "sha256_of"]

# The file name `roco-env train-detector` writes into its output folder.
WEIGHTS_FILE = "bev_detector.pt"
# The shipped weights by fusion, each a train-detector output folder under weights/ (with its
# report): "gated", the default, is "max" (the detector alone) plus a learned fusion gate.
SHIPPED_WEIGHTS = {"gated": f"gated/{WEIGHTS_FILE}", "max": WEIGHTS_FILE}
# A decoded box is labelled with the true object whose centre is nearest, within this
# distance (m): ground truth for the privileged info only, never used by the model.
_LABEL_GATE = 2.0


def shipped_weights_path(fusion: str = "gated") -> Path:
    """Path of the shipped weights with the given intermediate fusion: ``"gated"`` (the
    default weights: the detector and its learned fusion gate) or ``"max"`` (the detector
    alone, fused by the plain maximum); ValueError for another name."""
    if fusion not in SHIPPED_WEIGHTS:
        raise ValueError(f"shipped weights exist for fusion {sorted(SHIPPED_WEIGHTS)}; "
                         f"got {fusion!r}")
    return Path(str(resources.files("roco_env.sensing.learned") / "weights"
                    / SHIPPED_WEIGHTS[fusion]))


def sha256_of(path: str | Path) -> str:
    """Hex sha256 of a file's bytes."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


@dataclass(frozen=True)
class Checkpoint:
    """A loaded weights file: network shape, grid, scan noise, state dict, metadata."""

    net: NetConfig
    grid: BevGrid
    noise: ScanNoise
    state_dict: dict[str, torch.Tensor]
    meta: dict[str, Any]


def save_checkpoint(path: str | Path, net: BevDetectorNet, grid: BevGrid, noise: ScanNoise,
                    meta: dict[str, Any]) -> None:
    """Write a weights file (plain tensors and builtins only, loadable with weights_only)."""
    payload = {
        "format": "roco-env-bev-detector/1",
        "net": net.config.to_dict(),
        "grid": {"x_range": list(grid.x_range), "y_range": list(grid.y_range),
                 "resolution": grid.resolution},
        "channels": list(LIDAR_CHANNELS),
        "noise": {k: float(getattr(noise, k)) for k in ScanNoise.__dataclass_fields__},
        "state_dict": {k: v.detach().cpu().clone() for k, v in net.state_dict().items()},
        "meta": meta,
    }
    torch.save(payload, Path(path))


def load_checkpoint(path: str | Path) -> Checkpoint:
    """Read and check a weights file; ValueError naming the problem when it is unusable."""
    path = Path(path)
    if not path.exists():
        raise ValueError(f"learned detector weights file {path} does not exist")
    if not path.is_file():
        raise ValueError(f"learned detector weights file {path} is not a file")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for a damaged or foreign file
        # Only the type: torch's message suggests weights_only=False, which is never safe
        # for a file a user hands over.
        raise ValueError(f"learned detector weights file {path} is corrupt or not a weights "
                         f"file written by 'roco-env train-detector' "
                         f"({type(exc).__name__})") from exc
    if not isinstance(payload, dict) or payload.get("format") != "roco-env-bev-detector/1":
        raise ValueError(f"learned detector weights file {path} is not a roco-env BEV detector "
                         "checkpoint (missing format 'roco-env-bev-detector/1')")
    channels = tuple(payload.get("channels", ()))
    if channels != LIDAR_CHANNELS:
        raise ValueError(
            f"learned detector weights file {path} was trained on raster channels "
            f"{list(channels)} ({len(channels)}); this version rasterises {list(LIDAR_CHANNELS)} "
            f"({len(LIDAR_CHANNELS)}): retrain with 'roco-env train-detector'")
    try:
        net = NetConfig.from_dict(payload["net"])
        g = payload["grid"]
        grid = BevGrid(tuple(g["x_range"]), tuple(g["y_range"]), g["resolution"])
        noise = ScanNoise(**payload["noise"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"learned detector weights file {path} has invalid metadata: "
                         f"{exc}") from exc
    if net.in_channels != len(LIDAR_CHANNELS):
        raise ValueError(f"learned detector weights file {path} expects {net.in_channels} input "
                         f"channels; the LiDAR raster has {len(LIDAR_CHANNELS)}")
    if grid.H % 4 or grid.W % 4:
        raise ValueError(f"learned detector weights file {path}: grid {grid.H} x {grid.W} cells "
                         "must be multiples of 4 on both axes")
    state_dict = payload.get("state_dict")
    if not isinstance(state_dict, dict) or not all(
            isinstance(v, torch.Tensor) for v in state_dict.values()):
        raise ValueError(f"learned detector weights file {path} has no state_dict of tensors")
    non_finite = _non_finite_tensors(state_dict)
    if non_finite:
        # A NaN weight scores every box NaN: no detection passes, every reward is 0.
        raise ValueError(f"learned detector weights file {path} holds non-finite (NaN or inf) "
                         f"values in {', '.join(non_finite)}: retrain with 'roco-env "
                         "train-detector'")
    return Checkpoint(net, grid, noise, state_dict, dict(payload.get("meta", {})))


def _non_finite_tensors(state_dict: dict[str, torch.Tensor]) -> list[str]:
    """Names of the floating-point tensors (detector and fusion gate weights, buffers)
    holding a NaN or an infinity, in the state dict's order."""
    return [name for name, value in state_dict.items()
            if value.is_floating_point() and not bool(torch.isfinite(value).all())]


def build_network(checkpoint: Checkpoint, path: str | Path) -> BevDetectorNet:
    """The network of a checkpoint with its weights (ValueError on a shape mismatch)."""
    net = BevDetectorNet(checkpoint.net)
    try:
        net.load_state_dict(checkpoint.state_dict)
    except RuntimeError as exc:
        raise ValueError(f"learned detector weights file {path} does not match its declared "
                         f"network {checkpoint.net} (another grid or channel count?): "
                         f"{exc}") from exc
    return net.eval()


@dataclass(frozen=True)
class EncoderMaps:
    """Every agent's encoder map of a step, (A, C, h, w), on one feature ``grid`` (each map
    in its own agent's true sensor frame; zero beyond the agent's own raster)."""

    maps: torch.Tensor
    grid: BevGrid


def covering_grid(grid: BevGrid, x_range: Sequence[float], y_range: Sequence[float],
                  stride: int = 2) -> BevGrid:
    """``grid`` (a raster of the detector) grown by the same whole number of feature cells
    (``stride`` raster cells) on both sides of each axis until it covers ``x_range`` x
    ``y_range`` (m, agent frame); never shrunk. Growing symmetrically by feature cells keeps
    the cell counts multiples of 4, as the encoder needs."""
    step = grid.resolution * stride

    def cells(low: float, high: float, covered: Sequence[float]) -> int:
        need = max(low - covered[0], covered[1] - high, 0.0)
        return math.ceil(need / step - 1e-6)

    kx = cells(*grid.x_range, x_range)
    ky = cells(*grid.y_range, y_range)
    return BevGrid((grid.x_range[0] - kx * step, grid.x_range[1] + kx * step),
                   (grid.y_range[0] - ky * step, grid.y_range[1] + ky * step), grid.resolution)


class LearnedDetector:
    """Boxes, scores and uncertainties of every agent from the network, batched per step.

    weights: a weights file (default: the shipped one with its fusion gate); device:
    ``"cpu"`` or ``"cuda"``; score_threshold: minimum heatmap score of a decoded box;
    threads: CPU threads of the network (torch's intra-op count, set process-wide with
    ``torch.set_num_threads`` when the detector is built) and of intermediate fusion's
    compiled pass; gate: intermediate fusion through the weights' learned fusion gate
    (None: when they hold one; True: they must; False: the plain maximum). The values are
    checked against
    :class:`~roco_env.sensing.learned_params.LearnedDetectorParams` (ValueError naming the parameter).
    region: ``(x_range, y_range)`` (m, agent frame), the part of an agent's surroundings
    that is scored (the scenario's evaluation range). With it, an agent's raster is the
    trained grid grown to cover the agent's sensor range within the region
    (:meth:`raster_grid`): the network is convolutional, so an RSU whose LiDAR reaches
    100 m detects out to 100 m with weights trained on a 70.4 m grid, as OpenCOOD-style
    models read their dataset's whole perception range. Without it every raster is the
    trained grid. Agents with the same raster go through the network in one batch.
    box_sigma_xy (m) / box_sigma_yaw (rad): extra Gaussian noise on the centre (each axis)
    and heading of every box an agent reports and shares, with its reported uncertainty
    widened to match (added in quadrature, so it stays calibrated); the feature maps that
    intermediate fusion decodes are untouched. This is the precision of the boxes the
    aligners and late fusion work from: 0 (default) keeps the network's own, whose two
    views of one car differ by a median 0.26 m on ``v2xset_like``; the RoCo paper's
    Table 1 losses fit 0.3 m / 1.5 deg (docs/perception.md, "Box precision").
    The default, one thread, is the safe choice: more threads pay off only on an idle
    CPU and lose several times over on one busy with other jobs (measured in
    docs/perception.md, "Threads"). The network's outputs differ
    between thread counts at float32 rounding (the fused maps do not), so results repeat
    bit for bit on the same count. In a process forked from one that has run torch on
    more than one thread keep one: more hang in torch there (a sweep's local workers
    start from a fork server, which runs none).
    The network runs with its batch norms folded into the convolutions, channels-last.
    """

    #: The yaw is learned up to the front/back symmetry of a box (a LiDAR raster of a
    #: box shows none), so the env exchanges these headings in one half-turn convention
    #: (:func:`roco_env.geometry.canonical_axial_yaw`).
    axial_headings = True

    def __init__(self, weights: str | Path | None = None, device: str = "cpu",
                 score_threshold: float = SCORE_THRESHOLD, threads: int = 1,
                 gate: bool | None = None, box_sigma_xy: float = 0.0, box_sigma_yaw: float = 0.0,
                 region: tuple[Sequence[float], Sequence[float]] | None = None) -> None:
        params = _checked({"weights": None if weights is None else str(weights),
                           "device": device, "score_threshold": score_threshold,
                           "threads": threads, "gate": gate, "box_sigma_xy": box_sigma_xy,
                           "box_sigma_yaw": box_sigma_yaw})
        if params.device == "cuda" and not torch.cuda.is_available():
            raise ValueError("learned detector device='cuda' but torch sees no CUDA device")
        #: CPU threads of the network (torch, process-wide) and of intermediate fusion.
        self.threads = params.threads
        torch.set_num_threads(self.threads)
        path = Path(weights) if weights is not None else shipped_weights_path()
        self.checkpoint = load_checkpoint(path)
        self.net = build_network(self.checkpoint, path).for_inference().to(
            params.device, memory_format=torch.channels_last)
        self.device = torch.device(params.device)
        if params.gate and self.net.gate is None:
            raise ValueError(f"learned detector weights file {path} holds no fusion gate "
                             "(detector.params.gate=true); train one with 'roco-env "
                             "train-detector --fusion gated'")
        #: The learned fusion gate intermediate fusion uses (None: the plain maximum).
        self.gate = None if params.gate is False else self.net.gate
        self.grid = self.checkpoint.grid
        self.feature_grid = feature_grid(self.grid, self.checkpoint.net.stride)
        self.noise = self.checkpoint.noise
        self.score_threshold = params.score_threshold
        #: Extra box noise (std of x, y in m and of yaw in rad), see the class docstring.
        self.box_sigma = np.array([params.box_sigma_xy, params.box_sigma_xy,
                                   params.box_sigma_yaw])
        self.region = None if region is None else _checked_region(region)

    def raster_grid(self, sensor_range: float) -> BevGrid:
        """The raster of an agent whose sensor reaches ``sensor_range`` m: the trained grid
        (:attr:`grid`), grown to cover the square of that half-width clipped to
        :attr:`region` (:func:`covering_grid`); the trained grid without a region."""
        if self.region is None:
            return self.grid
        (x0, x1), (y0, y1) = self.region
        r = float(sensor_range)
        return covering_grid(self.grid, (max(-r, x0), min(r, x1)), (max(-r, y0), min(r, y1)),
                             self.checkpoint.net.stride)

    def rasters(self, state: WorldState, visibility: Visibility,
                rng: np.random.Generator) -> torch.Tensor:
        """Every agent's LiDAR raster (A, C, H, W) on the trained grid, scans drawn from
        ``rng``."""
        scans = sample_scans(state, visibility, self.noise, rng)
        return torch.from_numpy(lidar_rasters(scans, visibility.ray_ranges, self.grid))

    @torch.inference_mode()
    def encode(self, rasters: torch.Tensor) -> torch.Tensor:
        """Encoder maps (A, C, h, w) on :attr:`feature_grid`, on the detector's device."""
        return self.net.encode(rasters.to(self.device, memory_format=torch.channels_last))

    @torch.inference_mode()
    def decode(self, features: torch.Tensor, grounds: np.ndarray,
               grid: BevGrid | None = None) -> list[Decoded]:
        """Boxes of each feature map (own or fused) in its agent's frame.

        grid: the maps' grid when it is not :attr:`feature_grid` (a larger fusion
        canvas with the same cell size); grounds (N,): ground reference heights (m).
        """
        grid = grid or self.feature_grid
        if grid.resolution != self.feature_grid.resolution or features.shape[-2:] != (
                grid.H, grid.W):
            raise ValueError(f"features of shape {tuple(features.shape)} do not lie on a grid "
                             f"of {grid.H} x {grid.W} cells of {self.feature_grid.resolution} m")
        return decode(self.net.decode(features.to(self.device,
                                                  memory_format=torch.channels_last)), grid,
                      np.asarray(grounds, dtype=float), self.score_threshold)

    def perceive(self, state: WorldState, visibility: Visibility, rng: np.random.Generator
                 ) -> Perception:
        """Per agent its detections (true sensor frame), and all encoder maps, each agent read
        on its :meth:`raster_grid`; the maps are zero-padded onto the widest of them."""
        grids = [self.raster_grid(r) for r in np.asarray(state.sensor_ranges).reshape(-1)]
        widest = max(grids, key=lambda g: (g.W, g.H), default=self.grid)
        wide = feature_grid(widest, self.checkpoint.net.stride)
        if state.num_agents == 0:
            empty = torch.zeros((0, self.checkpoint.net.widths[2], wide.H, wide.W))
            return Perception([], EncoderMaps(empty, wide))
        scans = sample_scans(state, visibility, self.noise, rng)
        grounds = ground_references(state)
        groups: dict[BevGrid, list[int]] = {}
        for agent, grid in enumerate(grids):
            groups.setdefault(grid, []).append(agent)
        decoded: list[Decoded | None] = [None] * state.num_agents
        parts = []
        for grid, rows in groups.items():
            raster = lidar_rasters([scans[a] for a in rows], visibility.ray_ranges[rows], grid)
            features = self.encode(torch.from_numpy(raster))
            fgrid = feature_grid(grid, self.checkpoint.net.stride)
            for agent, boxes in zip(rows, self.decode(features, grounds[rows], fgrid),
                                    strict=True):
                decoded[agent] = boxes
            parts.append((rows, features, fgrid))
        maps = parts[0][1] if len(parts) == 1 else _on_one_grid(parts, wide, state.num_agents)
        detections = [self._labelled(state, a, d) for a, d in enumerate(decoded)]
        if self.box_sigma.any():
            # From a child stream (spawning one draws nothing from ``rng``): the scans of
            # this and every later step are those of the same episode without the noise.
            (box_rng,) = rng.spawn(1)
            detections = [_blurred(d, self.box_sigma, box_rng) for d in detections]
        return Perception(detections, EncoderMaps(maps, wide))

    def detect(self, state: WorldState, visibility: Visibility,
               rng: np.random.Generator) -> list[AgentDetections]:
        """One :class:`AgentDetections` per agent (the parametric detector's interface)."""
        return self.perceive(state, visibility, rng).detections

    def _labelled(self, state: WorldState, agent: int, decoded: Decoded) -> AgentDetections:
        return AgentDetections(decoded.boxes, decoded.uncertainty, decoded.scores,
                               label_boxes(state, agent, decoded.boxes))


def _blurred(detections: AgentDetections, sigma: np.ndarray,
             rng: np.random.Generator) -> AgentDetections:
    """One agent's ``detections`` (its true sensor frame) with N(0, sigma) added to each
    box's centre x, y (m) and heading (rad), sigma = (sigma_x m, sigma_y m, sigma_yaw rad),
    and sigma added in quadrature to the box's reported (sigma_x, sigma_y, sigma_yaw).
    Three normals per box from ``rng`` (none for an agent without boxes); z, sizes, scores
    and labels unchanged (a label names the object a box detects). Headings are left
    unwrapped: the pipeline puts them in its axial convention when it builds the views."""
    boxes = detections.boxes.copy()
    boxes[:, [0, 1, 6]] += rng.standard_normal((boxes.shape[0], 3)) * sigma
    return AgentDetections(boxes, np.hypot(detections.uncertainty, sigma), detections.scores,
                           detections.object_ids)


def _checked_region(region) -> tuple[tuple[float, float], tuple[float, float]]:
    """``region`` as ((x_min, x_max), (y_min, y_max)) floats; ValueError unless each is a
    finite pair with min < max."""
    try:
        (x0, x1), (y0, y1) = ((float(lo), float(hi)) for lo, hi in region)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"learned detector region must be ((x_min, x_max), (y_min, y_max)) in "
                         f"m; got {region!r}") from exc
    if not all(map(math.isfinite, (x0, x1, y0, y1))) or x0 >= x1 or y0 >= y1:
        raise ValueError(f"learned detector region must hold finite (min, max) pairs with "
                         f"min < max; got {region!r}")
    return (x0, x1), (y0, y1)


@torch.inference_mode()
def _on_one_grid(parts: list[tuple[list[int], torch.Tensor, BevGrid]], grid: BevGrid,
                 n_agents: int) -> torch.Tensor:
    """Maps (n_agents, C, H, W), channels-last, on ``grid`` from groups (agent rows, their
    maps, the maps' feature grid, inside ``grid`` on its cells,
    :func:`~roco_env.sensing.features.placement`), zero where a map does not reach."""
    first = parts[0][1]
    maps = torch.empty((n_agents, first.shape[1], grid.H, grid.W), dtype=first.dtype,
                       device=first.device, memory_format=torch.channels_last).zero_()
    for rows, features, fgrid in parts:
        cells_y, cells_x = placement(fgrid, grid)
        maps[rows, :, cells_y, cells_x] = features
    return maps


def label_boxes(state: WorldState, agent: int, boxes: np.ndarray) -> np.ndarray:
    """True object id of each box (agent frame), -1 for a false positive.

    One-to-one assignment by BEV centre distance (Hungarian), gated at 2 m;
    the agent's own vehicle is never a label.
    """
    ids = np.full(boxes.shape[0], -1, dtype=np.int64)
    others = np.flatnonzero(state.object_ids != state.agent_object_ids[agent])
    if not boxes.shape[0] or not others.size:
        return ids
    truth = transform_boxes(np.asarray(state.object_boxes)[others],
                            se2_inverse(state.agent_poses[agent]))
    dist = np.hypot(boxes[:, None, 0] - truth[None, :, 0], boxes[:, None, 1] - truth[None, :, 1])
    rows, cols = linear_sum_assignment(np.where(dist <= _LABEL_GATE, dist, 1e6))
    ok = dist[rows, cols] <= _LABEL_GATE
    ids[rows[ok]] = state.object_ids[others[cols[ok]]]
    return ids


def make_learned_detector(params: dict[str, Any] | None,
                          region: tuple[Sequence[float], Sequence[float]] | None = None
                          ) -> LearnedDetector:
    """The learned detector from scenario ``detector.params`` (the fields of
    :class:`~roco_env.sensing.learned_params.LearnedDetectorParams`) reading each agent's sensor range
    within ``region`` (see :class:`LearnedDetector`); ValueError naming an unknown key or
    a bad value."""
    return LearnedDetector(**dataclasses.asdict(_checked(dict(params or {}))), region=region)


def _checked(params: dict[str, Any]) -> LearnedDetectorParams:
    """``params`` checked against :class:`~roco_env.sensing.learned_params.LearnedDetectorParams`, the one
    place the learned detector's parameters are declared (scenario files use it too)."""
    return build(LearnedDetectorParams, params, "detector 'learned'", "detector.params.")
