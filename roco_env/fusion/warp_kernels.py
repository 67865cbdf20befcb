"""Compiled (numba) warp-and-max loop of intermediate fusion at run time.

:func:`roco_env.fusion.intermediate.fuse_on_canvas` resamples every collaborator's
encoder map into its ego's frame (bilinear, zero padding, cell centres as in torch's
``grid_sample`` with ``align_corners=False``) and takes the element-wise maximum with
the ego's map. ``grid_sample`` writes channel-planar maps (N, C, H, W) whatever its
input's layout, so with channels-last maps (what the detector's convolutions use) the
warp, the change of layout and the maximum were three passes over every warped cell.
This loop does all three in one pass, reading each source cell's channels contiguously
(and skipping the cells whose four neighbours all lie outside the source map); with a
learned fusion gate it warps into zeroed windows instead (the maps are non-negative, so
the maximum with zero is the warped value) and the gate and maximum follow in torch. Source
positions and bilinear weights are computed in float64, the weighted sums in float32 as
``grid_sample`` does; ``grid_sample`` computes the positions in float32, so the warped
values differ from its by up to about 5e-6 of their magnitude (2e-5 on the shipped
detector's maps, which reach about 9; tested against the torch path, ``fuse_maps``).
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
    acc = np.empty(n_ch, dtype=np.float32)
    for k in range(theta.shape[0]):
        src = features[rows[k]]
        dst = canvas[owner[k]]
        t = theta[k]
        # Source position in cells (cell centres at integer + 0.5, align_corners=False) of
        # output cell (i, j): normalised x_n = (2 j + 1) / width - 1, y_n = (2 i + 1) / out_h - 1,
        # mapped by t, then x = ((x_src + 1) w - 1) / 2: affine in (i, j).
        x_j, y_j = t[0, 0] * w / width, t[1, 0] * h / width
        x_i, y_i = t[0, 1] * w / out_h, t[1, 1] * h / out_h
        x_c = 0.5 * w * (t[0, 2] + 1.0 - t[0, 0] - t[0, 1]) - 0.5
        y_c = 0.5 * h * (t[1, 2] + 1.0 - t[1, 0] - t[1, 1]) - 0.5
        for i in range(out_h):
            x_row = x_c + x_i * (i + 0.5)
            y_row = y_c + y_i * (i + 0.5)
            for j in range(width):
                x = x_row + x_j * (j + 0.5)
                y = y_row + y_j * (j + 0.5)
                x0, y0 = math.floor(x), math.floor(y)
                if x0 < -1.0 or x0 >= w or y0 < -1.0 or y0 >= h:
                    continue  # all four neighbours outside the source map: adds zero
                fx, fy = x - x0, y - y0
                ix, iy = int(x0), int(y0)
                out = dst[i, first[k] + j]
                if 0 <= ix < w - 1 and 0 <= iy < h - 1:  # all four neighbours inside
                    w00 = np.float32((1.0 - fy) * (1.0 - fx))
                    w01 = np.float32((1.0 - fy) * fx)
                    w10 = np.float32(fy * (1.0 - fx))
                    w11 = np.float32(fy * fx)
                    s0, s1 = src[iy], src[iy + 1]
                    for ch in range(n_ch):
                        value = (w00 * s0[ix, ch] + w01 * s0[ix + 1, ch]
                                 + w10 * s1[ix, ch] + w11 * s1[ix + 1, ch])
                        if value > out[ch]:
                            out[ch] = value
                    continue
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
                        weight = np.float32(wy * (fx if dx else 1.0 - fx))
                        for ch in range(n_ch):
                            acc[ch] += weight * src[yy, xx, ch]
                for ch in range(n_ch):
                    if acc[ch] > out[ch]:
                        out[ch] = acc[ch]
