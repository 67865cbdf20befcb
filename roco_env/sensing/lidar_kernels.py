"""Compiled (numba) binning loop of the LiDAR rasters (:mod:`roco_env.sensing.lidar`).

One pass over a scan's points gives every cell's point count, height sum, highest
point and sums of the points' offsets inside the cell; the numpy path it replaced
needed a cell index array, a ``bincount`` per sum and a sort by cell for the per-cell
maximum (several times slower on 10^5 points). Sums run in float64 in point order, as
``bincount`` does, so the rasters equal the numpy path's bit for bit
(tests/test_sensing_lidar.py checks them against ``np.add.at`` accumulation).
"""

from __future__ import annotations

import math

from numba import njit

__all__ = ["bin_points"]


@njit(cache=True)
def bin_points(x, y, z, x_min, y_min, resolution, rows, cols, count, total, top, offset_x,
               offset_y):  # pragma: no cover
    """Accumulate points (x, y (P,) m in the grid's frame, z (P,) m) into flat (rows * cols,)
    cell arrays, in place: count (int), total (sum of z), top (max of z and 0), offset_x /
    offset_y (sums of the points' offsets from their cell's centre, in cells), float64.

    Cell (r, c) covers x in [x_min + c * resolution, ...) and y in [y_min + r * resolution,
    ...), flat index r * cols + c; points outside the grid are skipped.
    """
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
