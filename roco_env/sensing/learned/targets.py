"""Boxes <-> head maps of the learned detector: training targets and decoding.

Feature cells: the detector grid at ``stride`` times its raster cell size
(:meth:`feature_grid`), the same axis convention as the rasters. An object is
assigned to the feature cell holding its BEV centre; its heatmap target is a
Gaussian bump around that cell (CenterNet), its offset the centre's position
inside the cell, in cells. Decoding inverts this: heatmap peaks (3x3 local
maxima) above a score threshold, centre = cell corner + offset, then a BEV NMS
(one batched NMS for all maps of a batch, the same result as one ``nms_bev`` per map).
Boxes are (x, y, z, l, w, h, yaw) in the agent's frame, metres and radians.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from roco_env.batched_nms import batched_nms_bev
from roco_env.sensing.features import BevGrid

__all__ = ["Decoded", "Targets", "build_targets", "decode", "feature_grid"]

# Decoding: at most this many peaks per map, kept when the score exceeds the threshold,
# then BEV NMS at this IoU (duplicates of one object on neighbouring cells). At 0.2 the
# shipped weights keep about 33 boxes per agent on urban_intersection, against about 100
# at 0.05: less work for NMS, the policies and the AP matching.
MAX_PEAKS = 128
SCORE_THRESHOLD = 0.2
NMS_IOU = 0.1


def feature_grid(grid: BevGrid, stride: int) -> BevGrid:
    """The grid of the feature maps: same extent, ``stride`` times coarser cells."""
    return BevGrid(grid.x_range, grid.y_range, grid.resolution * stride)


@dataclass(frozen=True)
class Targets:
    """Training targets of a batch (N maps of h x w feature cells, K objects in all).

    heatmap (N, 1, h, w) in [0, 1]; sample, row, col (K,) long: where each object's
    centre cell is; offset (K, 2) in cells; log_size (K, 3); yaw (K,) rad.
    """

    heatmap: torch.Tensor
    sample: torch.Tensor
    row: torch.Tensor
    col: torch.Tensor
    offset: torch.Tensor
    log_size: torch.Tensor
    yaw: torch.Tensor


def build_targets(boxes_per_map: list[np.ndarray], fgrid: BevGrid) -> Targets:
    """Targets for N maps; boxes_per_map[n] (K_n, 7) in that map's frame (outside: ignored)."""
    h, w, res = fgrid.H, fgrid.W, fgrid.resolution
    heat = np.zeros((len(boxes_per_map), 1, h, w), dtype=np.float32)
    parts: dict[str, list] = {k: [] for k in ("sample", "row", "col", "offset", "size", "yaw")}
    for n, boxes in enumerate(boxes_per_map):
        boxes = np.asarray(boxes, dtype=float).reshape(-1, 7)
        u = (boxes[:, 0] - fgrid.x_range[0]) / res
        v = (boxes[:, 1] - fgrid.y_range[0]) / res
        col, row = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        for k in np.flatnonzero(inside):
            # Bump width from the box footprint: about a third of its width in cells; the
            # bump is cut at 3 sigma (below 0.012), as CenterNet draws it.
            sigma = max(0.5, 0.35 * boxes[k, 4] / res)
            reach = int(np.ceil(3.0 * sigma))
            rows = np.arange(max(row[k] - reach, 0), min(row[k] + reach + 1, h))
            cols = np.arange(max(col[k] - reach, 0), min(col[k] + reach + 1, w))
            bump = np.exp(-((cols[None, :] - col[k]) ** 2 + (rows[:, None] - row[k]) ** 2)
                          / (2.0 * sigma**2)).astype(np.float32)
            window = heat[n, 0, rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]
            np.maximum(window, bump, out=window)
        parts["sample"].append(np.full(inside.sum(), n))
        parts["row"].append(row[inside])
        parts["col"].append(col[inside])
        parts["offset"].append(np.stack([u - col, v - row], axis=1)[inside])
        parts["size"].append(np.log(np.maximum(boxes[inside, 3:6], 0.1)))
        parts["yaw"].append(boxes[inside, 6])
    cat = {k: np.concatenate(v) if v else np.zeros(0) for k, v in parts.items()}
    return Targets(
        heatmap=torch.from_numpy(heat),
        sample=torch.as_tensor(cat["sample"], dtype=torch.long),
        row=torch.as_tensor(cat["row"], dtype=torch.long),
        col=torch.as_tensor(cat["col"], dtype=torch.long),
        offset=torch.as_tensor(cat["offset"].reshape(-1, 2), dtype=torch.float32),
        log_size=torch.as_tensor(cat["size"].reshape(-1, 3), dtype=torch.float32),
        yaw=torch.as_tensor(cat["yaw"], dtype=torch.float32),
    )


@dataclass(frozen=True)
class Decoded:
    """One map's boxes (P, 7) in its frame (z from ``ground``), scores (P,), sigmas (P, 3)."""

    boxes: np.ndarray
    scores: np.ndarray
    uncertainty: np.ndarray


def _max_3x3(maps: torch.Tensor) -> torch.Tensor:
    """Maximum over each cell's 3 x 3 neighbourhood of maps (N, h, w), what
    ``max_pool2d(kernel 3, stride 1, padding 1)`` gives, as two separable passes of
    element-wise maxima (faster on one-channel maps on the CPU: docs/performance.md)."""
    p = F.pad(maps, (1, 1, 1, 1), value=-float("inf"))
    rows = torch.maximum(torch.maximum(p[:, :, :-2], p[:, :, 1:-1]), p[:, :, 2:])
    return torch.maximum(torch.maximum(rows[:, :-2], rows[:, 1:-1]), rows[:, 2:])


def decode(maps: dict[str, torch.Tensor], fgrid: BevGrid, grounds: np.ndarray,
           score_threshold: float = SCORE_THRESHOLD) -> list[Decoded]:
    """Boxes of every map of a batch of head outputs (see the module docstring).

    grounds (N,): world height of each agent's ground reference (m); a box's z
    is its centre height above it (boxes sit on the agent's ground plane).
    """
    heat = torch.sigmoid(maps["heatmap"][:, 0])
    peaks = heat * (heat == _max_3x3(heat))
    n, h, w = peaks.shape
    k = min(MAX_PEAKS, h * w)
    scores, flat = torch.topk(peaks.reshape(n, -1), k, dim=1)
    # Only the peaks above the threshold are gathered and turned into boxes, all maps at once.
    sample_t, rank_t = torch.nonzero(scores > score_threshold, as_tuple=True)
    flat = flat[sample_t, rank_t]
    row, col = flat // w, flat % w

    def at(name: str) -> np.ndarray:
        return maps[name][sample_t, :, row, col].detach().cpu().double().numpy()  # (P, c)

    offset, size, yaw, log_sigma = at("offset"), np.exp(at("size")), at("yaw"), at("log_sigma")
    sample, row_np, col_np = (t.cpu().numpy() for t in (sample_t, row, col))
    x = fgrid.x_range[0] + (col_np + offset[:, 0]) * fgrid.resolution
    y = fgrid.y_range[0] + (row_np + offset[:, 1]) * fgrid.resolution
    length, width, height = size.T
    boxes = np.column_stack([x, y, np.asarray(grounds, dtype=float)[sample] + 0.5 * height,
                             length, width, height, np.arctan2(yaw[:, 0], yaw[:, 1])])
    sc = scores[sample_t, rank_t].detach().cpu().numpy().astype(float)
    sig = np.exp(log_sigma)
    bounds = np.searchsorted(sample, np.arange(n + 1))
    spans = list(zip(bounds[:-1].tolist(), bounds[1:].tolist(), strict=True))
    kept = batched_nms_bev([boxes[lo:hi] for lo, hi in spans], [sc[lo:hi] for lo, hi in spans],
                           NMS_IOU)
    return [Decoded(boxes[lo + keep].reshape(-1, 7), sc[lo + keep], sig[lo + keep].reshape(-1, 3))
            for (lo, _), keep in zip(spans, kept, strict=True)]
