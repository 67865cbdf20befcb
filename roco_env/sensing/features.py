"""BEV feature maps per agent (torch) and their warping between agent frames.

Maps are float32 tensors (C, H, W) on a :class:`~roco_env.sensing.bev_grid.BevGrid`, in
an agent's sensor frame, with that module's axis convention (used by
:func:`bev_features` and :func:`warp_bev` alike). Values live at cell centres, which
is exactly torch's ``align_corners=False`` convention, so :func:`warp_bev` uses
``align_corners=False``.

Channels (:data:`CHANNELS`):
  0 ``log_returns``: log(1 + expected LiDAR returns falling in the cell), from
    simulated returns at the entry points of the rays on visible vehicle surfaces;
  1 ``max_height``: highest visible point of those surfaces in the cell (m above
    ground, 0 where no return);
  2 ``observed``: 1 where the cell centre lies on a ray before (or at) its first
    footprint hit and within sensor range (free space seen by the sensor), else 0.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from roco_env.sensing.bev_grid import BevGrid, affine_theta, cell_polar
from roco_env.sensing.visibility import Visibility

__all__ = ["CHANNELS", "BevGrid", "bev_features", "placement", "warp_bev", "zero_padded"]

CHANNELS = ("log_returns", "max_height", "observed")


def bev_features(visibility: Visibility, agent_index: int, grid: BevGrid) -> torch.Tensor:
    """BEV map (len(CHANNELS), H, W) float32 of one agent, in its true sensor frame.

    visibility: from :func:`compute_visibility`; agent_index: row of the agent.
    """
    n_agents, n_rays = visibility.ray_ranges.shape
    if not 0 <= agent_index < n_agents:
        raise ValueError(f"agent_index must be in [0, {n_agents}); got {agent_index}")
    hits = visibility.hits
    mine = hits.agent == agent_index
    row, col = grid.cell_index(hits.x[mine], hits.y[mine])
    inside = row >= 0
    cell = row[inside] * grid.W + col[inside]
    n_cells = grid.H * grid.W
    out = np.zeros((len(CHANNELS), n_cells), dtype=np.float32)
    out[0] = np.log1p(np.bincount(cell, weights=hits.returns[mine][inside], minlength=n_cells))
    np.maximum.at(out[1], cell, hits.top[mine][inside])
    radius, ray = cell_polar(grid, n_rays)
    out[2] = radius <= visibility.ray_ranges[agent_index][ray]
    return torch.from_numpy(out.reshape(len(CHANNELS), grid.H, grid.W))


def warp_bev(features: torch.Tensor, T_src_to_dst: np.ndarray | torch.Tensor,  # noqa: N803
             grid: BevGrid, out_grid: BevGrid | None = None) -> torch.Tensor:
    """Resample BEV maps from a source agent frame into a destination frame.

    features: (C, H, W) or (N, C, H, W) on ``grid`` in the source frame;
    T_src_to_dst: pose (3,) or (N, 3) (x m, y m, yaw rad) mapping source-frame
    points into the destination frame (e.g. a corrected T_{j->i}). Output: the
    same maps on ``out_grid`` (default ``grid``; any extent and cell size) in the
    destination frame: bilinear ``grid_sample``, zero padding outside the source
    map, ``align_corners=False``.
    """
    single = features.dim() == 3
    batch = features.unsqueeze(0) if single else features
    if batch.dim() != 4 or batch.shape[-2:] != (grid.H, grid.W):
        raise ValueError(
            f"features must have shape (C, {grid.H}, {grid.W}) or (N, C, {grid.H}, {grid.W}) "
            f"for this grid; got {tuple(features.shape)}"
        )
    poses = np.asarray(torch.as_tensor(T_src_to_dst).detach().cpu(), dtype=float)
    if poses.shape[-1:] != (3,) or poses.size != 3 * batch.shape[0] or not np.all(
            np.isfinite(poses)):
        raise ValueError(
            f"T_src_to_dst must be {batch.shape[0]} finite pose(s) (x, y, yaw); "
            f"got shape {tuple(np.shape(T_src_to_dst))}"
        )
    out_grid = out_grid or grid
    theta = torch.from_numpy(affine_theta(poses.reshape(-1, 3), grid, out_grid)).to(
        dtype=batch.dtype, device=batch.device)
    sample_at = F.affine_grid(theta, [*batch.shape[:2], out_grid.H, out_grid.W],
                              align_corners=False)
    warped = F.grid_sample(batch, sample_at, mode="bilinear", padding_mode="zeros",
                           align_corners=False)
    return warped[0] if single else warped


def placement(grid: BevGrid, target: BevGrid) -> tuple[slice, slice]:
    """The (row, column) slices of ``target`` that ``grid`` covers, ``target`` being a grid
    of the same cells that contains it; ValueError otherwise."""
    res = grid.resolution
    edges = ((grid.x_range[0] - target.x_range[0]), (target.x_range[1] - grid.x_range[1]),
             (grid.y_range[0] - target.y_range[0]), (target.y_range[1] - grid.y_range[1]))
    pads = tuple(round(e / res) for e in edges)
    if target.resolution != res or min(pads) < 0 or any(
            abs(e - p * res) > 1e-6 for e, p in zip(edges, pads, strict=True)):
        raise ValueError(f"grid {target} must contain the feature grid {grid} on its cells "
                         "(same cell size, whole-cell margins)")
    left, bottom = pads[0], pads[2]
    return slice(bottom, bottom + grid.H), slice(left, left + grid.W)


def zero_padded(maps: torch.Tensor, grid: BevGrid, target: BevGrid) -> torch.Tensor:
    """Maps (N, C, H, W) on ``grid`` placed on ``target`` (:func:`placement`), zero elsewhere
    (exact: a map holds nothing beyond its grid), in the maps' memory format (torch's pad
    returns channels-last maps as contiguous ones, and their copy back costs as much again)."""
    rows, cols = placement(grid, target)
    layout = (torch.channels_last if maps.dim() == 4 and not maps.is_contiguous()
              and maps.is_contiguous(memory_format=torch.channels_last)
              else torch.contiguous_format)
    out = torch.empty((maps.shape[0], maps.shape[1], target.H, target.W), dtype=maps.dtype,
                      device=maps.device, memory_format=layout).zero_()
    out[:, :, rows, cols] = maps
    return out
