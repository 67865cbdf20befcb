"""The BEV raster grid shared by LiDAR rasters, BEV features and the learned detector (numpy).

Axis convention: a map (C, H, W) on a :class:`BevGrid` lies in an agent's sensor
frame; row ``r`` covers ``y in [y_min + r*res, y_min + (r+1)*res)`` and column ``c``
covers ``x in [x_min + c*res, x_min + (c+1)*res)`` (row 0 at the most negative y, i.e.
the right-hand side of the agent; column 0 at the most negative x, behind it). Values
live at cell centres (torch's ``align_corners=False`` convention).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

__all__ = ["BevGrid", "affine_theta", "cell_polar"]


def _as_float(value: object) -> float:
    """float(value), or NaN when it is not a real number (rejected by the caller)."""
    try:
        return float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return math.nan


@dataclass(frozen=True)
class BevGrid:
    """A BEV raster: x_range, y_range (min, max) in metres (agent frame), cell size in m.

    The grid covers [x_min, x_min + W*res) x [y_min, y_min + H*res) with
    W = round((x_max - x_min) / res) columns and H = round((y_max - y_min) / res) rows.
    """

    x_range: tuple[float, float]
    y_range: tuple[float, float]
    resolution: float = 0.4

    def __post_init__(self) -> None:
        resolution = _as_float(self.resolution)
        if not resolution > 0.0 or not math.isfinite(resolution):
            raise ValueError(f"BevGrid.resolution must be a finite number > 0 m; "
                             f"got {self.resolution!r}")
        object.__setattr__(self, "resolution", resolution)
        for name in ("x_range", "y_range"):
            value = getattr(self, name)
            bounds = tuple(_as_float(v) for v in value) if np.ndim(value) == 1 else ()
            # at least one cell, up to float rounding of a span built as min + k * res
            if not (len(bounds) == 2 and all(map(math.isfinite, bounds))
                    and bounds[1] - bounds[0] >= resolution * (1.0 - 1e-9)):
                raise ValueError(
                    f"BevGrid.{name} must be (min, max) finite with max - min >= resolution "
                    f"({resolution} m); got {value!r}"
                )
            object.__setattr__(self, name, bounds)

    @classmethod
    def square(cls, half_extent: float, resolution: float = 0.4) -> BevGrid:
        """Grid over [-half_extent, half_extent] on both axes (e.g. the sensor range)."""
        return cls((-half_extent, half_extent), (-half_extent, half_extent), resolution)

    @property
    def H(self) -> int:  # noqa: N802 (the conventional tensor dimension name)
        return int(round((self.y_range[1] - self.y_range[0]) / self.resolution))

    @property
    def W(self) -> int:  # noqa: N802
        return int(round((self.x_range[1] - self.x_range[0]) / self.resolution))

    def cell_index(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(row, col) int arrays of points (m); -1 in both where outside the grid."""
        col = np.floor((np.asarray(x) - self.x_range[0]) / self.resolution).astype(np.int64)
        row = np.floor((np.asarray(y) - self.y_range[0]) / self.resolution).astype(np.int64)
        inside = (col >= 0) & (col < self.W) & (row >= 0) & (row < self.H)
        return np.where(inside, row, -1), np.where(inside, col, -1)


@lru_cache(maxsize=8)
def cell_polar(grid: BevGrid, n_rays: int) -> tuple[np.ndarray, np.ndarray]:
    """Flat (H*W,) distance (m) and ray index of every cell centre (cached per grid)."""
    xs = grid.x_range[0] + (np.arange(grid.W) + 0.5) * grid.resolution
    ys = grid.y_range[0] + (np.arange(grid.H) + 0.5) * grid.resolution
    x, y = np.meshgrid(xs, ys)  # (H, W): rows along y, columns along x
    step = 2.0 * np.pi / n_rays
    ray = np.mod(np.rint(np.arctan2(y, x) / step).astype(np.int64), n_rays)
    return np.hypot(x, y).ravel(), ray.ravel()


def affine_theta(poses: np.ndarray, grid: BevGrid, out_grid: BevGrid) -> np.ndarray:
    """Matrices (N, 2, 3) of torch's ``affine_grid`` (``align_corners=False``) that sample a
    source map on ``grid`` at T^-1 * (cell centre of ``out_grid``): normalised output
    coordinates to normalised source coordinates. poses (N, 3): T (x m, y m, yaw rad)
    mapping source-frame points into the output frame."""
    def half_and_centre(g: BevGrid) -> tuple[np.ndarray, np.ndarray]:
        half = np.array([g.W * g.resolution, g.H * g.resolution]) / 2.0
        return half, np.array([g.x_range[0], g.y_range[0]]) + half

    half, centre = half_and_centre(grid)
    out_half, out_centre = half_and_centre(out_grid)
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    # Inverse pose dst -> src: p_src = A p_dst + b with A = R^T, b = -R^T t.
    a = np.stack([np.stack([c, s], -1), np.stack([-s, c], -1)], axis=1)  # (N, 2, 2)
    b = -np.einsum("nij,nj->ni", a, poses[:, :2])
    # Normalised coordinates: p = half * n + centre on each grid.
    lin = a * out_half[None, None, :] / half[None, :, None]
    shift = (np.einsum("nij,j->ni", a, out_centre) + b - centre) / half
    return np.concatenate([lin, shift[:, :, None]], axis=2)
