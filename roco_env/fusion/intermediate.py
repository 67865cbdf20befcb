"""Intermediate fusion: warp collaborators' BEV feature maps into the ego frame, max-fuse, decode.

Each collaborator's map (C, h, w), in its own true sensor frame on the shared
feature grid, is resampled into the ego frame with the *corrected* relative
pose T_{j->i} (bilinear, zero padding, via :func:`roco_env.sensing.warp_bev`)
and fused with the ego's map by an element-wise maximum (the maps are
non-negative, so the zero padding outside a collaborator's view adds nothing); a
network with a learned gate (:class:`~roco_env.sensing.learned.network.FusionGate`)
first weighs each warped map, cell by cell, against the ego's own map.
:func:`intermediate_fusion` then decodes the fused maps with the learned
detector's heads: a wrong pose misaligns the maps before decoding, so it
shows up in the boxes and their AP. Needs torch (imported on demand by the env).
"""

from __future__ import annotations

import functools
import math
import os
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import torch

from roco_env.fusion.late import EGO_SOURCE, FusedDetections, kept_items
from roco_env.fusion.warp_kernels import Gate, Warp, warp_gate_max_into, warp_max_into
from roco_env.sensing import BevGrid, warp_bev
from roco_env.sensing.bev_grid import affine_theta
from roco_env.sensing.features import zero_padded
from roco_env.sensing.learned.network import FusionGate
from roco_env.sensing.lidar import ground_references
from roco_env.traffic.state import WorldState

__all__ = ["fuse_features", "fuse_maps", "fuse_on_canvas", "fusion_canvas",
           "intermediate_fusion"]


def fuse_maps(features: torch.Tensor, egos: Sequence[int], collaborators: Sequence[Sequence[int]],
              poses: Sequence[np.ndarray], grid: BevGrid,
              canvas: BevGrid | None = None, gate: FusionGate | None = None) -> torch.Tensor:
    """Max-fused maps (E, C, H, W) on ``canvas`` (default ``grid``), all egos in one warp;
    differentiable (the training path; :func:`fuse_on_canvas` is the run-time one).

    features (N, C, h, w) on ``grid``, one per agent; egos: rows of the egos;
    collaborators[e]: rows of ego e's collaborators; poses[e] (n_e, 3): the
    T_{j->e} (x m, y m, yaw rad) its collaborators' maps are warped with; canvas: a
    grid of ``grid``'s cells containing it (:func:`fusion_canvas`); gate: a
    :class:`~roco_env.sensing.learned.network.FusionGate` weighing every warped map
    against its ego's own map before the maximum (None: the plain maximum).
    """
    canvas = canvas or grid
    own, rows, poses = _own_on_canvas(features, egos, collaborators, poses, grid, canvas)
    if not rows:
        return own
    warped = warp_bev(features[rows], np.concatenate(poses), grid, canvas)
    if gate is not None:
        warped = warped * gate(own[[e for e, c in enumerate(collaborators) for _ in c]], warped)
    per_ego = torch.split(warped, [len(c) for c in collaborators])
    return torch.stack([torch.maximum(mine, theirs.amax(dim=0)) if theirs.shape[0] else mine
                        for mine, theirs in zip(own, per_ego, strict=True)])


def fuse_on_canvas(features: torch.Tensor, egos: Sequence[int],
                   collaborators: Sequence[Sequence[int]], poses: Sequence[np.ndarray],
                   grid: BevGrid, canvas: BevGrid | None = None,
                   gate: FusionGate | None = None, threads: int = 1) -> torch.Tensor:
    """:func:`fuse_maps` at run time (no autograd: writes in place), on ``canvas``.

    Max-fused maps (E, C, H, W) on ``canvas`` (default ``grid``), all egos in one warp.

    features (N, C, h, w) on ``grid``, one per agent; egos: rows of the egos;
    collaborators[e]: rows of ego e's collaborators; poses[e] (n_e, 3): the
    T_{j->e} (x m, y m, yaw rad) its collaborators' maps are warped with; canvas:
    a grid of ``grid``'s cells containing it (:func:`fusion_canvas`): the egos' own maps
    are zero-padded onto it, the collaborators' maps warped straight onto it; gate: as
    in :func:`fuse_maps`; threads: CPU threads of the compiled pass, each on a band of
    canvas rows (the result does not depend on it).
    """
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise ValueError(f"threads must be an integer >= 1; got {threads!r}")
    canvas = canvas or grid
    own, rows, poses = _own_on_canvas(features, egos, collaborators, poses, grid, canvas)
    if not rows:
        return own
    # Each map is warped onto a window of canvas columns covering its footprint (at most
    # 161 of the 281.6 m of the default canvas), each shifted to its own first column,
    # then max-ed into its ego's map.
    all_poses = np.concatenate(poses)
    first, window = _footprint_columns(all_poses, grid, canvas)
    shifted = all_poses.copy()
    shifted[:, 0] -= first * canvas.resolution
    owner = [e for e, c in enumerate(collaborators) for _ in c]
    if not (features.device.type == "cpu" and features.dtype == torch.float32):
        return _max_into(own, warp_bev(features[rows], shifted, grid, window), owner, first,
                         gate)
    # Compiled pass (roco_env.fusion.warp_kernels) on channels-last maps: warp, gate and
    # max straight into the egos' maps (the gate reads a copy of them from before).
    own = own.contiguous(memory_format=torch.channels_last)
    cells = own.permute(0, 2, 3, 1).numpy()
    sources = features.contiguous(memory_format=torch.channels_last).permute(0, 2, 3, 1).numpy()
    warp = tuple(Warp(sources, affine_theta(shifted, grid, window), np.asarray(rows),
                      np.asarray(owner), first, window.W))
    if gate is None:
        def fuse_band(band: np.ndarray) -> None:
            warp_max_into(cells, warp, band)
    else:
        weights = Gate(*gate.cell_weights())
        if weights.w_in.shape[0] != 3 * features.shape[1]:  # the compiled pass trusts it
            raise ValueError(f"the fusion gate reads {weights.w_in.shape[0] // 3} channels; "
                             f"the maps have {features.shape[1]}")
        before, weights = cells.copy(), tuple(weights)

        def fuse_band(band: np.ndarray) -> None:
            warp_gate_max_into(cells, before, warp, band, weights)
    bands = _row_bands(cells.shape[1], threads)
    if len(bands) == 1:
        fuse_band(bands[0])
    else:  # the kernels release the GIL; the bands' rows are disjoint
        list(_band_pool(len(bands)).map(fuse_band, bands))
    return own


def _row_bands(rows: int, threads: int) -> list[np.ndarray]:
    """``rows`` canvas rows split into at most ``threads`` (>= 1) contiguous (start, stop)
    bands."""
    edges = np.linspace(0, rows, min(threads, rows) + 1).round().astype(np.int64)
    return [edges[b:b + 2].copy() for b in range(len(edges) - 1)]


@functools.cache
def _band_pool(threads: int) -> ThreadPoolExecutor:
    """One pool per thread count, kept for the process (threads idle between steps).

    A forked child (of a user's own ``fork``) starts without them: the pools are forgotten
    there (below), or its first multi-thread fusion would queue bands on a pool whose
    threads do not exist in it, and wait forever.
    """
    return ThreadPoolExecutor(max_workers=threads, thread_name_prefix="roco-fusion")


os.register_at_fork(after_in_child=_band_pool.cache_clear)


def _own_on_canvas(features: torch.Tensor, egos: Sequence[int],
                   collaborators: Sequence[Sequence[int]], poses: Sequence[np.ndarray],
                   grid: BevGrid, canvas: BevGrid
                   ) -> tuple[torch.Tensor, list[int], list[np.ndarray]]:
    """The egos' own maps zero-padded onto ``canvas`` (E, C, H, W), the rows of all their
    collaborators' maps in order, and the checked poses (the common start of both fusions)."""
    own = zero_padded(features[list(egos)], grid, canvas)
    poses = _checked_poses(egos, collaborators, poses)
    return own, [j for c in collaborators for j in c], poses


def _max_into(own: torch.Tensor, warped: torch.Tensor, owner: Sequence[int], first: np.ndarray,
              gate: FusionGate | None) -> torch.Tensor:
    """``own`` with every warped window map k (K, C, H, w) max-ed into own[owner[k]] at
    canvas columns first[k] .. first[k] + w, in place, each weighed first by ``gate``
    against its ego's own map on its window (read before any collaborator is max-ed in)."""
    width = warped.shape[-1]
    if gate is not None:
        mine = torch.stack([own[e, :, :, start:start + width]
                            for e, start in zip(owner, first.tolist(), strict=True)])
        warped = warped * gate(mine, warped)
    for k, (e, start) in enumerate(zip(owner, first.tolist(), strict=True)):
        cols = own[e, :, :, start:start + width]
        torch.maximum(cols, warped[k], out=cols)
    return own


def _footprint_columns(poses: np.ndarray, grid: BevGrid, canvas: BevGrid
                       ) -> tuple[np.ndarray, BevGrid]:
    """First canvas column of each warped map's window (N,) and the window grid (the
    canvas's first columns, as wide as the widest footprint): a map on ``grid`` moved by
    pose (x, y, yaw) is non-zero only inside its rectangle grown by one cell (bilinear)."""
    res = canvas.resolution
    xs = np.array([grid.x_range[0] - res, grid.x_range[1] + res])
    ys = np.array([grid.y_range[0] - res, grid.y_range[1] + res])
    cx, cy = (a.ravel() for a in np.meshgrid(xs, ys))
    c, s = np.cos(poses[:, 2:3]), np.sin(poses[:, 2:3])
    x_dst = c * cx - s * cy + poses[:, 0:1]  # (N, 4) corners in the destination frame
    low = np.floor((x_dst.min(axis=1) - canvas.x_range[0]) / res).astype(np.int64)
    high = np.ceil((x_dst.max(axis=1) - canvas.x_range[0]) / res).astype(np.int64)
    low, high = np.clip(low, 0, canvas.W), np.clip(high, 0, canvas.W)
    width = int(np.clip((high - low).max(), 1, canvas.W))
    first = np.minimum(low, canvas.W - width)
    window = BevGrid((canvas.x_range[0], canvas.x_range[0] + width * res), canvas.y_range, res)
    return first, window


def _checked_poses(egos: Sequence[int], collaborators: Sequence[Sequence[int]],
                   poses: Sequence[np.ndarray]) -> list[np.ndarray]:
    """poses as (n_e, 3) float arrays; ValueError when the three lists do not match."""
    if not (len(egos) == len(collaborators) == len(poses)):
        raise ValueError(f"egos, collaborators and poses must have one entry per ego; got "
                         f"{len(egos)}, {len(collaborators)} and {len(poses)}")
    poses = [np.asarray(p, dtype=float).reshape(-1, 3) for p in poses]
    for e, (c, p) in enumerate(zip(collaborators, poses, strict=True)):
        if p.shape[0] != len(c):
            raise ValueError(f"poses[{e}] must hold one pose per collaborator map; got "
                             f"{p.shape[0]} poses for {len(c)} maps")
    return poses


def fuse_features(ego_features: torch.Tensor, collab_features: Sequence[torch.Tensor],
                  relative_poses: np.ndarray, grid: BevGrid) -> torch.Tensor:
    """Max-fused map (C, H, W) of one ego; relative_poses (N, 3): T_{j->i} per collaborator."""
    relative_poses = np.asarray(relative_poses, dtype=float).reshape(-1, 3)
    if relative_poses.shape[0] != len(collab_features):
        raise ValueError(
            "relative_poses must hold one pose per collaborator map; got "
            f"{relative_poses.shape[0]} poses for {len(collab_features)} maps"
        )
    stacked = torch.stack([ego_features, *collab_features])
    return fuse_maps(stacked, [0], [list(range(1, stacked.shape[0]))], [relative_poses], grid)[0]


def fusion_canvas(grid: BevGrid, x_range: Sequence[float], y_range: Sequence[float]
                  ) -> tuple[BevGrid, tuple[int, int, int, int]]:
    """The smallest grid of ``grid``'s cells covering ``grid`` and the given ranges (m).

    Returns the canvas and the whole cells (left, right, bottom, top) it adds on each
    side, so a map on ``grid`` is placed on the canvas by zero padding (exact: the map
    is zero outside its own extent anyway).
    """
    res = grid.resolution
    pads = (max(0, math.ceil((grid.x_range[0] - x_range[0]) / res - 1e-6)),
            max(0, math.ceil((x_range[1] - grid.x_range[1]) / res - 1e-6)),
            max(0, math.ceil((grid.y_range[0] - y_range[0]) / res - 1e-6)),
            max(0, math.ceil((y_range[1] - grid.y_range[1]) / res - 1e-6)))
    canvas = BevGrid((grid.x_range[0] - pads[0] * res, grid.x_range[1] + pads[1] * res),
                     (grid.y_range[0] - pads[2] * res, grid.y_range[1] + pads[3] * res), res)
    return canvas, pads


def intermediate_fusion(detector, encoder_maps, state: WorldState,
                        egos: Sequence[int], collaborators: Sequence[Sequence[int]],
                        poses: Sequence[np.ndarray], x_range: Sequence[float],
                        y_range: Sequence[float]) -> list[FusedDetections]:
    """Decoded boxes of every ego's fused map, in its true frame (scores descending).

    detector: a :class:`roco_env.sensing.learned.LearnedDetector`; encoder_maps: its
    :class:`~roco_env.sensing.learned.model.EncoderMaps` of this step (every agent's map on
    one feature grid); egos, collaborators (agent indices) and
    poses (the corrected T_{j->i}) as in :func:`fuse_maps`. The maps are fused on a
    canvas covering that grid and the ego-frame range ``x_range`` x ``y_range``
    (m; the evaluation range), so a collaborator's view beyond the ego's own sensor grid
    is decoded too (the heads are convolutional); the detector's fusion gate, if its
    weights hold one, weighs the warped maps. Every box's source is the ego
    (:data:`EGO_SOURCE`): it comes from the ego's fused map.
    """
    grid = encoder_maps.grid
    canvas, _ = fusion_canvas(grid, x_range, y_range)
    with torch.inference_mode():
        fused = fuse_on_canvas(encoder_maps.maps, egos, collaborators, poses, grid, canvas,
                               detector.gate, detector.threads)
    decoded = detector.decode(fused, ground_references(state)[list(egos)], canvas)
    return [FusedDetections(d.boxes, d.scores, np.full(len(d.scores), EGO_SOURCE, dtype=np.int64),
                            np.arange(len(d.scores), dtype=np.int64)) for d in decoded]


class IntermediateFusion:
    """``intermediate``: the kept collaborators' encoder maps warped into the ego's, fused
    and decoded by the learned detector (:func:`intermediate_fusion`) over the
    evaluation range."""

    def __init__(self, config: Any, detector: Any) -> None:
        self.detector = detector
        self.x_range = tuple(config.evaluation.x_range)
        self.y_range = tuple(config.evaluation.y_range)

    def fuse(self, frame: Any, egos: Sequence[int], kept: Sequence[np.ndarray],
             poses: Sequence[np.ndarray]) -> list[FusedDetections]:
        return intermediate_fusion(
            self.detector, frame.encoder_maps, frame.state, egos,
            [kept_items(_map_rows(frame.views[k]), keep) for k, keep in zip(egos, kept,
                                                                            strict=True)],
            poses, self.x_range, self.y_range)


def _map_rows(view: Any) -> tuple[int, ...]:
    """The rows of the frame's encoder maps holding each collaborator slot's map: the slots'
    agents, or the delivered maps' rows under the network stage (roco_env.comm)."""
    rows = getattr(view, "collab_map_rows", None)
    return view.collaborators if rows is None else rows
