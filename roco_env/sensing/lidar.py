"""Simulated LiDAR scans and their BEV rasters: the input of the learned detector.

A scan is drawn per agent from the ray model of :mod:`roco_env.sensing.visibility`
(numpy only, no torch). For every (ray, object) entry point that the ray model
says is seen, with ``lambda`` expected points (vertical beams on that azimuth):

* **Sampled returns.** The number of points is Poisson(``lambda * keep``), so
  far and occluded surfaces give few points and sometimes none (range-dependent
  sparsity comes from ``lambda``, which falls with distance);
* **dropouts.** ``keep = 1 - dropout - range_dropout * distance / 100 m``
  (clipped to [0, 1]): missed returns (dark paint, glass) that grow with range;
* each point lies on the entry point moved along the ray by N(0, ``range_noise``)
  metres, at a height uniform over the object's vertical extent;
* **spurious returns.** Poisson(``spurious_rate``) isolated points per scan,
  uniform over the sensor disk, heights uniform in [0, 2.5] m (dust, rain,
  reflections).

Heights are relative to the ground under the agent (``state.ground_heights``, the
datum of :mod:`roco_env.sensing.visibility` too: 0 in simulated scenes, LiDAR height
minus mast height in replays). So a detector sees the same heights for a car next to
it on a hill as on flat ground.

The raster (:data:`LIDAR_CHANNELS`, (C, H, W) float32 on a :class:`BevGrid`,
the axis convention of :mod:`roco_env.sensing.bev_grid`):
  0 ``log_points``: log(1 + sampled points in the cell);
  1 ``max_height``: highest point in the cell (m above the reference, 0 if none);
  2 ``mean_height``: mean point height in the cell (m, 0 if none);
  3 ``mean_dx``, 4 ``mean_dy``: mean offset of the cell's points from the cell centre along
    x and y, in cells (in [-0.5, 0.5], 0 if none): where in the cell the surface lies,
    which the cell grid alone would quantise away (the point decoration of PointPillars);
  5 ``observed``: 1 where the cell centre lies before the first surface hit on
    its ray and within sensor range (free space the sensor saw), else 0.
Draws come from the generator given, in a fixed order, so a seed fixes the scan.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from roco_env.sensing.bev_grid import BevGrid, cell_polar
from roco_env.sensing.lidar_kernels import Cells, CellSums, bin_points
from roco_env.sensing.visibility import Visibility
from roco_env.traffic.state import WorldState

__all__ = ["LIDAR_CHANNELS", "LidarScan", "ScanNoise", "ground_references", "lidar_raster",
           "lidar_rasters", "sample_scans"]

LIDAR_CHANNELS = ("log_points", "max_height", "mean_height", "mean_dx", "mean_dy", "observed")

# Height span (m) of spurious returns.
_SPURIOUS_TOP = 2.5


@dataclass(frozen=True)
class ScanNoise:
    """Imperfections of the simulated scans (see the module docstring for the model).

    dropout: share of returns lost at any range; range_dropout: extra share lost
    per 100 m of distance; range_noise: std of the range error, m;
    spurious_rate: mean number of spurious points per scan.
    """

    dropout: float = 0.05
    range_dropout: float = 0.15
    range_noise: float = 0.03
    spurious_rate: float = 40.0

    def __post_init__(self) -> None:
        for name, high in (("dropout", 1.0), ("range_dropout", 1.0), ("range_noise", 5.0),
                           ("spurious_rate", 1.0e5)):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value)
                    and 0.0 <= value <= high):
                raise ValueError(f"ScanNoise.{name} must be in [0, {high}]; got {value!r}")


@dataclass(frozen=True)
class LidarScan:
    """One agent's sampled points in its true sensor frame (N of them).

    x, y (N,) m; z (N,) m above the agent's ground reference; obj (N,) object
    index of the surface hit (into the WorldState objects), -1 for spurious points.
    """

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    obj: np.ndarray


def ground_references(state: WorldState) -> np.ndarray:
    """(A,) world height (m) of the ground under each agent: ``state.ground_heights``, the
    datum visibility measures its heights from, so scans, rasters and decoded boxes share it."""
    return np.asarray(state.ground_heights, dtype=float).reshape(state.num_agents)


def sample_scans(state: WorldState, visibility: Visibility, noise: ScanNoise,
                 rng: np.random.Generator) -> list[LidarScan]:
    """One :class:`LidarScan` per agent (``state.agent_ids`` order), drawn from ``rng``."""
    hits = visibility.hits
    boxes = np.asarray(state.object_boxes, dtype=float).reshape(-1, 7)
    distance = np.hypot(hits.x, hits.y)
    keep = np.clip(1.0 - noise.dropout - noise.range_dropout * distance / 100.0, 0.0, 1.0)
    counts = rng.poisson(hits.returns * keep)
    pick = np.repeat(np.arange(counts.size), counts)
    along = 1.0 + noise.range_noise * rng.standard_normal(pick.size) / np.maximum(
        distance[pick], 1e-6)
    obj, agent = hits.obj[pick], hits.agent[pick]
    bottom = boxes[obj, 2] - 0.5 * boxes[obj, 5]
    # Visibility measures surface heights from the ground under the seeing agent; back to
    # world heights, like the box bottoms (the ground is subtracted again below).
    ground = ground_references(state)
    top = hits.top[pick] + ground[agent]
    height = bottom + rng.random(pick.size) * np.maximum(top - bottom, 0.0)
    x, y = hits.x[pick] * along, hits.y[pick] * along
    # Hits are sorted by agent (RayHits), so each agent's returns are one slice.
    bounds = np.searchsorted(agent, np.arange(state.num_agents + 1)).tolist()
    scans = []
    for a in range(state.num_agents):
        mine = slice(bounds[a], bounds[a + 1])
        n_fake = int(rng.poisson(noise.spurious_rate))
        radius = float(state.sensor_ranges[a]) * np.sqrt(rng.random(n_fake))
        bearing = rng.uniform(-np.pi, np.pi, n_fake)
        scans.append(LidarScan(
            x=np.concatenate([x[mine], radius * np.cos(bearing)]),
            y=np.concatenate([y[mine], radius * np.sin(bearing)]),
            z=np.concatenate([height[mine] - ground[a], rng.uniform(0.0, _SPURIOUS_TOP, n_fake)]),
            obj=np.concatenate([obj[mine], np.full(n_fake, -1, dtype=np.int64)]),
        ))
    return scans


def lidar_raster(scan: LidarScan, ray_ranges: np.ndarray, grid: BevGrid) -> np.ndarray:
    """BEV raster (len(LIDAR_CHANNELS), H, W) float32 of one scan.

    ray_ranges (n_rays,): the agent's first-hit distance per ray (m), i.e. a row
    of :attr:`Visibility.ray_ranges`.
    """
    return lidar_rasters([scan], np.asarray(ray_ranges)[None], grid)[0]


def lidar_rasters(scans: Sequence[LidarScan], ray_ranges: np.ndarray,
                  grid: BevGrid) -> np.ndarray:
    """BEV rasters (len(scans), len(LIDAR_CHANNELS), H, W) float32 of several scans at once
    (each equals :func:`lidar_raster` of its scan; points binned by a compiled loop,
    :mod:`roco_env.sensing.lidar_kernels`).

    ray_ranges (len(scans), n_rays): each scan's agent's first-hit distance per ray (m).
    """
    n = len(scans)
    ray_ranges = np.asarray(ray_ranges, dtype=float).reshape(n, -1)
    count = np.zeros((n, grid.H * grid.W), dtype=np.int64)
    total = np.zeros((n, grid.H * grid.W))
    top = np.zeros((n, grid.H * grid.W))  # highest point per cell, 0 when none is above 0
    offset_x, offset_y = np.zeros((n, grid.H * grid.W)), np.zeros((n, grid.H * grid.W))
    cells = tuple(Cells(float(grid.x_range[0]), float(grid.y_range[0]), float(grid.resolution),
                        int(grid.H), int(grid.W)))
    for k, scan in enumerate(scans):
        bin_points(np.asarray(scan.x, dtype=float), np.asarray(scan.y, dtype=float),
                   np.asarray(scan.z, dtype=float), cells,
                   tuple(CellSums(count[k], total[k], top[k], offset_x[k], offset_y[k])))
    per_cell = np.maximum(count, 1)
    out = np.empty((n, len(LIDAR_CHANNELS), grid.H, grid.W), dtype=np.float32)
    out[:, 0] = np.log1p(count).reshape(n, grid.H, grid.W)
    out[:, 1] = top.reshape(n, grid.H, grid.W)
    out[:, 2] = (total / per_cell).reshape(n, grid.H, grid.W)
    out[:, 3] = (offset_x / per_cell).reshape(n, grid.H, grid.W)
    out[:, 4] = (offset_y / per_cell).reshape(n, grid.H, grid.W)
    radius, ray = cell_polar(grid, ray_ranges.shape[1])
    out[:, 5] = (radius[None, :] <= ray_ranges[:, ray]).reshape(n, grid.H, grid.W)
    return out
