"""Training of the learned BEV detector (``roco-env train-detector``).

Every step takes ``scenes_per_step`` training scenes (:mod:`.data`), mirrors
each at random (x and/or y axis, the same for all its agents, poses included),
encodes all their agents in one batch and sums two losses:

* **single-agent**: each agent's map decoded against its own targets; with
  ``warp_augment`` > 0 that share of the maps is first warped by a random rigid
  motion (any heading, a shift of up to one feature cell) and decoded against its
  boxes on the map moved alike, so the network learns maps that can be read after a
  resampling and a rotation, as the fused ones are;
* **fused**: for every agent as an ego, its collaborators' maps warped into its
  frame with the relative poses (true, or perturbed by N(0, ``pose_sigma_t``) m
  per axis and N(0, ``pose_sigma_r``) deg when training for pose noise), fused
  by element-wise max with its own (after a learned per-cell weight on each
  collaborator's map with ``fusion="gated"``), decoded against the collaboration's targets,
  on the detector grid or on a larger canvas (``fused_x_range`` x ``fused_y_range``,
  the env's evaluation range), where a collaborator's view beyond the ego's grid is
  decoded as the env decodes it.

A run starts from random weights or from a weights file (``init``); with
``train_encoder=False`` the encoder is frozen (eval mode, no gradients) and only the
trunk and heads learn: a fine-tuning stage that leaves every agent's encoder map as
it was; with ``train_detector=False`` (``fusion="gated"``) the whole detector is frozen
and only the fusion gate learns, from the fused loss alone.

Loss per decoded map set: CenterNet focal loss on the heatmap; at object
centre cells L1 on the offset and log size, L1 on (sin, cos) of the yaw up to
the box's front/back symmetry (the smaller of the two L1s), and the Gaussian
negative log-likelihood 0.5 (e / sigma)^2 + log sigma of the centre (x, y, m)
and yaw errors with the errors detached, so the uncertainty head learns the
spread of the regressors without pulling them. AdamW with a one-cycle
learning-rate schedule. Deterministic: numpy and torch seeded from ``seed``,
``torch.use_deterministic_algorithms(True)``, a fixed thread count.
"""

from __future__ import annotations

import math
import multiprocessing
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np
import torch
import torch.nn.functional as F

from roco_env.fusion.intermediate import fuse_maps, fusion_canvas
from roco_env.geometry import se2_compose, transform_boxes, wrap_angle
from roco_env.metrics import APAccumulator
from roco_env.sensing.features import BevGrid, warp_bev
from roco_env.sensing.learned.model import Checkpoint, build_network, load_checkpoint
from roco_env.sensing.learned.network import BevDetectorNet, NetConfig
from roco_env.sensing.learned.targets import Targets, build_targets, decode, feature_grid
from roco_env.sensing.lidar import LIDAR_CHANNELS
from roco_env.training.data import (
    TRAIN_SEED_BASE,
    VALIDATION_SEED_BASE,
    WORKER_CONTEXT,
    Scene,
    make_scenes,
)
from roco_env.training.detector_config import TrainConfig

__all__ = ["TrainResult", "evaluate", "feature_grid_of", "fused_canvas", "init_checkpoint",
           "mirror_rasters", "set_determinism", "train"]

# Loss weights: heatmap, offset, size, yaw, uncertainty NLL.
_WEIGHTS = {"heatmap": 1.0, "offset": 1.0, "size": 1.0, "yaw": 1.0, "nll": 0.2}


def feature_grid_of(config: TrainConfig) -> BevGrid:
    """The encoder map's grid of ``config`` (the network's stride on ``config.grid``)."""
    return feature_grid(config.grid, NetConfig().stride)


def fused_canvas(config: TrainConfig) -> BevGrid:
    """The grid the fused loss decodes on: :func:`feature_grid_of` grown to cover
    ``fused_x_range`` x ``fused_y_range`` (m)."""
    fgrid = feature_grid_of(config)
    return fusion_canvas(fgrid, config.fused_x_range or fgrid.x_range,
                         config.fused_y_range or fgrid.y_range)[0]


@dataclass
class TrainResult:
    """The trained network, its loss history (per step, by term) and validation metrics."""

    net: BevDetectorNet
    history: dict[str, list[float]]
    validation: dict[str, float]
    seconds: float
    config: TrainConfig

    def summary(self) -> dict:
        return {"config": _jsonable(asdict(self.config)), "validation": self.validation,
                "seconds": round(self.seconds, 1),
                "parameters": sum(p.numel() for p in self.net.parameters()),
                "final_loss": self.history["total"][-1] if self.history["total"] else None}


def _jsonable(value):
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    return value


def set_determinism(seed: int, threads: int, device: str = "cpu") -> None:
    """Seed torch, force deterministic kernels and fix the CPU thread count.

    On CUDA every kernel is deterministic but the backward of ``grid_sample`` (the
    warp of the fused loss), which accumulates with atomic adds: a CUDA run is
    reproducible up to that rounding order, so torch is told to warn, not fail.
    """
    torch.manual_seed(seed)
    if device == "cuda":
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
        torch.backends.cudnn.benchmark = False
    torch.use_deterministic_algorithms(True, warn_only=device == "cuda")
    torch.set_num_threads(threads)


def _focal_loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """CenterNet focal loss (alpha 2, beta 4), normalised by the number of centres."""
    pred = torch.sigmoid(logits).clamp(1e-4, 1.0 - 1e-4)
    pos = target.eq(1.0).float()
    pos_loss = -torch.log(pred) * (1.0 - pred) ** 2 * pos
    neg_loss = -torch.log(1.0 - pred) * pred**2 * (1.0 - target) ** 4 * (1.0 - pos)
    return (pos_loss.sum() + neg_loss.sum()) / pos.sum().clamp(min=1.0)


def detection_loss(maps: dict[str, torch.Tensor], targets: Targets,
                   cell: float) -> dict[str, torch.Tensor]:
    """Loss terms (module docstring) of head maps against targets; cell: feature cell, m."""
    terms = {"heatmap": _focal_loss(maps["heatmap"], targets.heatmap.to(maps["heatmap"].device))}
    if targets.sample.numel() == 0:
        zero = maps["offset"].sum() * 0.0
        return {**terms, "offset": zero, "size": zero, "yaw": zero, "nll": zero}
    device = maps["offset"].device
    idx = (targets.sample.to(device), slice(None), targets.row.to(device), targets.col.to(device))
    offset, size = maps["offset"][idx], maps["size"][idx]
    yaw, log_sigma = maps["yaw"][idx], maps["log_sigma"][idx]
    true_yaw = targets.yaw.to(device)
    trig = torch.stack([torch.sin(true_yaw), torch.cos(true_yaw)], dim=1)
    yaw_l1 = torch.minimum((yaw - trig).abs().sum(1), (yaw + trig).abs().sum(1))
    err_xy = (offset - targets.offset.to(device)).detach() * cell
    pred_yaw = torch.atan2(yaw[:, 0], yaw[:, 1]).detach()
    # Axis error: the yaw regression is defined up to pi (front/back symmetry).
    err_yaw = torch.remainder(pred_yaw - true_yaw + math.pi / 2, math.pi) - math.pi / 2
    err = torch.cat([err_xy, err_yaw[:, None]], dim=1)
    nll = 0.5 * (err * torch.exp(-log_sigma)) ** 2 + log_sigma
    terms.update(offset=F.l1_loss(offset, targets.offset.to(device)),
                 size=F.l1_loss(size, targets.log_size.to(device)),
                 yaw=yaw_l1.mean(), nll=nll.mean())
    return terms


def mirror_rasters(rasters: torch.Tensor, flip_x: bool, flip_y: bool) -> torch.Tensor:
    """LiDAR rasters (N, C, H, W) of the scans mirrored along x and/or y (the detector grid
    is symmetric about the sensor): the cells flipped, and the point-offset channels
    (``mean_dx`` / ``mean_dy``, signed positions inside a cell) negated with them."""
    dims = [d for d, f in ((-1, flip_x), (-2, flip_y)) if f]
    if not dims:
        return rasters
    mirrored = torch.flip(rasters, dims)
    for flipped, channel in ((flip_x, "mean_dx"), (flip_y, "mean_dy")):
        if flipped:
            mirrored[:, LIDAR_CHANNELS.index(channel)] *= -1.0
    return mirrored


def _mirror(scene: Scene, flip_x: bool, flip_y: bool):
    """Rasters, per-agent boxes, group boxes and relative poses of a mirrored scene."""
    rasters = mirror_rasters(torch.from_numpy(scene.rasters), flip_x, flip_y)

    def boxes(b: np.ndarray) -> np.ndarray:
        b = b.copy()
        if flip_x:
            b[:, 0], b[:, 6] = -b[:, 0], np.pi - b[:, 6]
        if flip_y:
            b[:, 1], b[:, 6] = -b[:, 1], -b[:, 6]
        b[:, 6] = wrap_angle(b[:, 6])
        return b

    def pose(p: np.ndarray) -> np.ndarray:
        p = p.copy()
        for flipped, axis in ((flip_x, 0), (flip_y, 1)):
            if flipped:
                p[:, axis], p[:, 2] = -p[:, axis], -p[:, 2]
        return p

    return (rasters, [boxes(b) for b in scene.targets], [boxes(b) for b in scene.group_targets],
            [pose(p) for p in scene.relative])


@dataclass(frozen=True)
class _Batch:
    """One training step's inputs: rasters (N, C, H, W), single-agent targets (of the maps
    as decoded: rows ``warped`` moved by ``warps`` (k, 3), x m, y m, yaw rad), and for the
    fused loss the ego rows, their collaborators' rows, the (noisy) poses and the targets."""

    rasters: torch.Tensor
    single: Targets
    warped: np.ndarray
    warps: np.ndarray
    egos: list[int]
    collaborators: list[list[int]]
    poses: list[np.ndarray]
    fused: Targets | None


class _Batches(torch.utils.data.Dataset):
    """Step s's batch, a pure function of (scenes, config, s): its scene picks, mirrors and
    pose noise come from rng((seed, s)), so any number of loader workers gives the same run."""

    def __init__(self, scenes: list[Scene], config: TrainConfig) -> None:
        self.scenes, self.config = scenes, config
        self.fgrid, self.canvas = feature_grid_of(config), fused_canvas(config)

    def __len__(self) -> int:
        return self.config.steps

    def __getitem__(self, step: int) -> _Batch:
        config = self.config
        rng = np.random.default_rng((config.seed, step))
        picks = rng.choice(len(self.scenes), size=min(config.scenes_per_step, len(self.scenes)),
                           replace=False)
        rasters, singles, groups, egos, collabs, poses = [], [], [], [], [], []
        offset = 0
        for scene in (self.scenes[i] for i in picks):
            r, single, group, rel = _mirror(scene, bool(rng.random() < 0.5),
                                            bool(rng.random() < 0.5))
            rasters.append(r)
            singles += single
            for a, c in enumerate(scene.collaborators):
                if not c:
                    continue
                egos.append(offset + a)
                collabs.append([offset + j for j in c])
                noise = np.column_stack([
                    rng.normal(0.0, config.pose_sigma_t, (len(c), 2)),
                    rng.normal(0.0, np.deg2rad(config.pose_sigma_r), len(c))])
                poses.append(se2_compose(noise, rel[a]).reshape(-1, 3))
                groups.append(group[a])
            offset += r.shape[0]
        warped, warps = self._warps(rng, len(singles))
        for k, pose in zip(warped, warps, strict=True):
            # Only boxes on the map have features to move: a box off the grid (which
            # build_targets drops unwarped) must not land on the warp's zero padding.
            on_map = self.fgrid.cell_index(singles[k][:, 0], singles[k][:, 1])[0] >= 0
            singles[k] = transform_boxes(singles[k][on_map], pose)
        return _Batch(torch.cat(rasters), build_targets(singles, self.fgrid), warped, warps,
                      egos, collabs, poses,
                      build_targets(groups, self.canvas) if egos else None)

    def _warps(self, rng: np.random.Generator, n_maps: int) -> tuple[np.ndarray, np.ndarray]:
        """Rows of the maps to warp and their motions: any heading, a shift of up to one
        feature cell per axis (drawn only when ``warp_augment`` > 0, so runs without it
        keep their random stream)."""
        if not self.config.warp_augment:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 3))
        rows = np.flatnonzero(rng.random(n_maps) < self.config.warp_augment)
        cell = self.fgrid.resolution
        warps = np.column_stack([rng.uniform(-cell, cell, (rows.size, 2)),
                                 rng.uniform(-np.pi, np.pi, rows.size)])
        return rows, warps


def _as_is(batch: _Batch) -> _Batch:
    """The loader's collate function: a step's batch is already whole."""
    return batch


def train(config: TrainConfig, progress: bool = True,
          log: Callable[[str], None] | None = None) -> TrainResult:
    """Generate the scenes, train the network, validate it (module docstring)."""
    if config.workers and WORKER_CONTEXT not in multiprocessing.get_all_start_methods():
        raise ValueError(f"workers={config.workers} needs the {WORKER_CONTEXT!r} start method, "
                         "which this platform lacks; use workers=0")
    if config.device == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device='cuda' (--device cuda) but torch {torch.__version__} sees no "
                         "CUDA device; use device='cpu'")
    previous = (torch.are_deterministic_algorithms_enabled(),
                torch.is_deterministic_algorithms_warn_only_enabled(), torch.get_num_threads(),
                torch.backends.cudnn.benchmark)
    try:
        return _train(config, progress, log)
    finally:  # leave the caller's torch settings as they were
        torch.use_deterministic_algorithms(previous[0], warn_only=previous[1])
        torch.set_num_threads(previous[2])
        torch.backends.cudnn.benchmark = previous[3]


def _train(config: TrainConfig, progress: bool,
           log: Callable[[str], None] | None) -> TrainResult:
    from tqdm import tqdm

    start = time.perf_counter()
    set_determinism(config.seed, config.threads, config.device)
    device = torch.device(config.device)
    grid = config.grid
    fgrid, canvas = feature_grid_of(config), fused_canvas(config)
    log = log or (lambda _msg: None)
    log(f"generating {config.train_scenes} training scenes")
    scenes = make_scenes(config.scenarios, config.train_scenes, TRAIN_SEED_BASE + config.seed,
                         grid, config.noise, progress, config.workers)
    net = _initial_network(config).to(device)
    _train_mode(net, config)
    trainable = [p for p in net.parameters() if p.requires_grad]
    optimiser = torch.optim.AdamW(trainable, lr=config.lr, weight_decay=1e-4)
    schedule = torch.optim.lr_scheduler.OneCycleLR(optimiser, config.lr, total_steps=config.steps,
                                                   pct_start=0.15)
    history: dict[str, list[float]] = {k: [] for k in ("total", "single", "fused", *_WEIGHTS)}
    loader = torch.utils.data.DataLoader(
        _Batches(scenes, config), batch_size=None, shuffle=False, num_workers=config.workers,
        collate_fn=_as_is, multiprocessing_context=WORKER_CONTEXT if config.workers else None,
        prefetch_factor=4 if config.workers else None)
    bar = tqdm(loader, desc="train-detector", disable=not progress, mininterval=5.0)
    for step, batch in enumerate(bar):
        with torch.set_grad_enabled(config.trains_encoder):
            features = net.encode(batch.rasters.to(device))
        single = detection_loss(net.decode(_warped(features, batch, fgrid)), batch.single,
                                fgrid.resolution)
        loss_single = sum(_WEIGHTS[k] * v for k, v in single.items())
        if batch.fused is not None:
            fused_maps = fuse_maps(features, batch.egos, batch.collaborators, batch.poses, fgrid,
                                   canvas, net.gate)
            fused = detection_loss(net.decode(fused_maps), batch.fused, fgrid.resolution)
            loss_fused = sum(_WEIGHTS[k] * v for k, v in fused.items())
        else:
            loss_fused = loss_single * 0.0
        loss = loss_single + loss_fused
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(trainable, 10.0)
        optimiser.step()
        schedule.step()
        history["total"].append(loss.item())
        history["single"].append(loss_single.item())
        history["fused"].append(loss_fused.item())
        for k in _WEIGHTS:
            history[k].append(single[k].item())
        if step % 10 == 9:
            bar.set_postfix(loss=f"{np.mean(history['total'][-10:]):.3f}", refresh=False)
    net.eval()
    validation: dict[str, float] = {}
    if config.val_scenes:
        log(f"validating on {config.val_scenes} scenes")
        val = make_scenes(config.val_scenarios, config.val_scenes,
                          VALIDATION_SEED_BASE + config.seed, grid, config.noise, progress,
                          config.workers)
        net_cpu = net.cpu()
        validation = evaluate(net_cpu, val, fgrid, canvas=canvas)
        if config.pose_sigma_t or config.pose_sigma_r:
            noisy = evaluate(net_cpu, val, fgrid, (config.pose_sigma_t, config.pose_sigma_r),
                             canvas=canvas)
            validation.update({f"noisy_{k}": v for k, v in noisy.items() if k.startswith("fused")})
    return TrainResult(net, history, validation, time.perf_counter() - start, config)


def _warped(features: torch.Tensor, batch: _Batch, fgrid: BevGrid) -> torch.Tensor:
    """The maps of the single-agent loss: ``features`` with the batch's warped rows moved."""
    if not batch.warped.size:
        return features
    maps = features.clone()
    maps[batch.warped] = warp_bev(features[batch.warped], batch.warps, fgrid)
    return maps


def init_checkpoint(config: TrainConfig) -> Checkpoint | None:
    """The weights file ``config.init`` (None without one), checked before any work: its
    network widths, grid and scan noise must be the run's, and a file with a fusion gate
    needs ``fusion="gated"`` (ValueError naming the mismatch); a gate-less file may start
    a gated run (the gate starts fresh)."""
    if config.init is None:
        return None
    checkpoint = load_checkpoint(config.init)
    for name, theirs, ours in (("widths", tuple(checkpoint.net.widths), tuple(config.widths)),
                               ("grid", checkpoint.grid, config.grid),
                               ("noise", checkpoint.noise, config.noise)):
        if theirs != ours:
            raise ValueError(f"init weights {config.init} were trained with {name} {theirs}; "
                             f"this run's {name} is {ours}")
    if checkpoint.net.fusion == "gated" and config.fusion != "gated":
        raise ValueError(f"init weights {config.init} hold a fusion gate; this run's fusion is "
                         f"{config.fusion!r}: use --fusion gated")
    return checkpoint


def _initial_network(config: TrainConfig) -> BevDetectorNet:
    """A randomly initialised network, or the one of ``config.init`` (:func:`init_checkpoint`),
    with a fresh fusion gate when the run adds one."""
    net = BevDetectorNet(NetConfig(len(LIDAR_CHANNELS), tuple(config.widths), config.fusion))
    checkpoint = init_checkpoint(config)
    if checkpoint is not None:
        started = build_network(checkpoint, config.init)
        net.load_state_dict({**net.state_dict(), **started.state_dict()})
    return net


def _train_mode(net: BevDetectorNet, config: TrainConfig) -> None:
    """Training mode; frozen parts (the encoder, or the whole detector) stay in eval mode
    (their batch norms keep their statistics) and get no gradients."""
    net.train()
    frozen = (net.detector_modules() if not config.train_detector
              else () if config.train_encoder else net.encoder_modules())
    for module in frozen:
        module.train(False).requires_grad_(False)


@torch.no_grad()
def evaluate(net: BevDetectorNet, scenes: list[Scene], fgrid: BevGrid,
             pose_noise: tuple[float, float] = (0.0, 0.0), seed: int = 0,
             canvas: BevGrid | None = None) -> dict[str, float]:
    """AP@0.3/0.5/0.7 of single-agent and fused (true or noisy poses; decoded on ``canvas``,
    default ``fgrid``) detection, and the share of matched centre/yaw errors within 1 and 2
    predicted sigmas (single agent, IoU >= 0.5)."""
    from roco_env.geometry import bev_iou

    rng = np.random.default_rng(seed)
    single_acc, fused_acc = APAccumulator(), APAccumulator()
    z_scores: list[np.ndarray] = []
    for scene in scenes:
        features = net.encode(torch.from_numpy(scene.rasters))
        for a, det in enumerate(decode(net.decode(features), fgrid, scene.grounds)):
            single_acc.add_frame(det.boxes, det.scores, scene.eval_gt[a])
            gt = scene.eval_gt[a]
            if det.boxes.shape[0] and gt.shape[0]:
                iou = bev_iou(det.boxes, gt)
                best = iou.argmax(axis=1)
                ok = iou[np.arange(len(best)), best] >= 0.5
                err = np.column_stack([
                    det.boxes[ok, :2] - gt[best[ok], :2],
                    np.remainder(det.boxes[ok, 6] - gt[best[ok], 6] + np.pi / 2, np.pi)
                    - np.pi / 2])
                z_scores.append(np.abs(err) / det.uncertainty[ok])
        egos = [a for a, c in enumerate(scene.collaborators) if c]
        if egos:
            poses = []
            for a in egos:
                n = len(scene.collaborators[a])
                noise = np.column_stack([rng.normal(0.0, pose_noise[0], (n, 2)),
                                         rng.normal(0.0, np.deg2rad(pose_noise[1]), n)])
                poses.append(se2_compose(noise, scene.relative[a]).reshape(-1, 3))
            fused = fuse_maps(features, egos, [list(scene.collaborators[a]) for a in egos],
                               poses, fgrid, canvas, net.gate)
            for a, det in zip(egos, decode(net.decode(fused), canvas or fgrid,
                                           scene.grounds[egos]),
                              strict=True):
                fused_acc.add_frame(det.boxes, det.scores, scene.group_eval_gt[a])
    out = {f"single_ap{round(t * 100)}": v for t, v in single_acc.ap().items()}
    out.update({f"fused_ap{round(t * 100)}": v for t, v in fused_acc.ap().items()})
    z = np.concatenate(z_scores) if z_scores else np.zeros((0, 3))
    for k, name in enumerate(("x", "y", "yaw")):
        out[f"within_1sigma_{name}"] = float(np.mean(z[:, k] <= 1.0)) if len(z) else math.nan
        out[f"within_2sigma_{name}"] = float(np.mean(z[:, k] <= 2.0)) if len(z) else math.nan
    return out
