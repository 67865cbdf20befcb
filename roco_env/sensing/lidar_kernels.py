"""Compiled (numba) binning loop of the LiDAR rasters (:mod:`roco_env.sensing.lidar`).

One pass over a scan's points gives every cell's point count, height sum, highest
point and sums of the points' offsets inside the cell; the numpy path it replaced
needed a cell index array, a ``bincount`` per sum and a sort by cell for the per-cell
maximum (several times slower on 10^5 points). Sums run in float64 in point order, as
``bincount`` does, so the rasters equal the numpy path's bit for bit
(tests/test_sensing_lidar.py checks them against ``np.add.at`` accumulation).

The kernel takes the grid as a :class:`Cells` record and the sums as a :class:`CellSums`
(``typing.NamedTuple``, defined here); from Python a record is passed as a plain tuple,
``tuple(record)``, which numba types in C, and named again on entry.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

__all__ = ["CellSums", "Cells", "bin_points"]


class Cells(NamedTuple):
    """A raster's cells: cell (r, c) covers x in [x_min + c * resolution, ...) and y in
    [y_min + r * resolution, ...) (m), ``rows`` x ``cols`` cells, flat index r * cols + c."""

    x_min: float
    y_min: float
    resolution: float
    rows: int
    cols: int


class CellSums(NamedTuple):
    """Flat (rows * cols,) per-cell sums of a scan's points: count (int64), total (sum of
    z), top (max of z and 0), offset_x / offset_y (sums of the points' offsets from their
    cell's centre, in cells), float64."""

    count: np.ndarray
    total: np.ndarray
    top: np.ndarray
    offset_x: np.ndarray
    offset_y: np.ndarray


@njit(cache=True)
def bin_points(x, y, z, cells, sums):  # pragma: no cover
    """Accumulate points (x, y (P,) m in the grid's frame, z (P,) m) into the
    :class:`CellSums` of the :class:`Cells`, in place; points outside the grid are
    skipped."""
    cells, sums = Cells(*cells), CellSums(*sums)
    x_min, y_min, resolution, rows, cols = (cells.x_min, cells.y_min, cells.resolution,
                                            cells.rows, cells.cols)
    count, total, top, offset_x, offset_y = (sums.count, sums.total, sums.top, sums.offset_x,
                                             sums.offset_y)
    for p in range(x.shape[0]):
        u = (x[p] - x_min) / resolution
        v = (y[p] - y_min) / resolution
        col = math.floor(u)
        row = math.floor(v)
        if col < 0 or col >= cols or row < 0 or row >= rows:
            continue
        cell = row * cols + col
        count[cell] += 1
        total[cell] += z[p]
        offset_x[cell] += u - col - 0.5
        offset_y[cell] += v - row - 0.5
        if z[p] > top[cell]:
            top[cell] = z[p]
