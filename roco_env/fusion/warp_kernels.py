"""Compiled (numba) warp-and-max loop of intermediate fusion at run time.

:func:`roco_env.fusion.intermediate.fuse_on_canvas` resamples every collaborator's
encoder map into its ego's frame (bilinear, zero padding, cell centres as in torch's
``grid_sample`` with ``align_corners=False``) and takes the element-wise maximum with
the ego's map. ``grid_sample`` writes channel-planar maps (N, C, H, W) whatever its
input's layout, so with channels-last maps (what the detector's convolutions use) the
warp, the change of layout and the maximum were three passes over every warped cell.
This loop does all three in one pass, reading each source cell's channels contiguously,
with coordinates and weights in float64: the warped values agree with ``grid_sample``'s
float32 ones to rounding (tested against the torch path, ``fuse_maps``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["warp_max_into"]


@njit(cache=True)
def warp_max_into(canvas, features, theta, rows, owner, first, width):  # pragma: no cover
    """Max each warped map into its ego's canvas map, in place.

    canvas (E, H, Wc, C) float32, channels last: the egos' maps (written);
    features (N, h, w, C) float32, channels last: the source maps; theta (K, 2, 3):
    ``affine_grid`` matrices mapping normalised coordinates of a ``width``-column window
    of the canvas (all H rows) to normalised source coordinates; map k is source
    ``rows[k]``, maxed into canvas ``owner[k]`` at columns first[k] .. first[k] + width.
    """
    out_h = canvas.shape[1]
    h, w, n_ch = features.shape[1], features.shape[2], features.shape[3]
    acc = np.empty(n_ch)
    for k in range(theta.shape[0]):
        src = features[rows[k]]
        dst = canvas[owner[k]]
        t = theta[k]
        for i in range(out_h):
            yn = (2.0 * i + 1.0) / out_h - 1.0
            for j in range(width):
                xn = (2.0 * j + 1.0) / width - 1.0
                # Source position in cells (cell centres at integer + 0.5, align_corners=False).
                x = ((t[0, 0] * xn + t[0, 1] * yn + t[0, 2] + 1.0) * w - 1.0) * 0.5
                y = ((t[1, 0] * xn + t[1, 1] * yn + t[1, 2] + 1.0) * h - 1.0) * 0.5
                x0, y0 = math.floor(x), math.floor(y)
                if x0 < -1.0 or x0 >= w or y0 < -1.0 or y0 >= h:
                    continue  # all four neighbours outside the source map: adds zero
                fx, fy = x - x0, y - y0
                ix, iy = int(x0), int(y0)
                acc[:] = 0.0
                for dy in range(2):
                    yy = iy + dy
                    if yy < 0 or yy >= h:
                        continue
                    wy = fy if dy else 1.0 - fy
                    for dx in range(2):
                        xx = ix + dx
                        if xx < 0 or xx >= w:
                            continue
                        weight = wy * (fx if dx else 1.0 - fx)
                        for ch in range(n_ch):
                            acc[ch] += weight * src[yy, xx, ch]
                col = first[k] + j
                for ch in range(n_ch):
                    value = np.float32(acc[ch])
                    if value > dst[i, col, ch]:
                        dst[i, col, ch] = value
