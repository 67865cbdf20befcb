"""Compiled (numba) warp-and-max loop of intermediate fusion at run time.

:func:`roco_env.fusion.intermediate.fuse_on_canvas` resamples every collaborator's
encoder map into its ego's frame (bilinear, zero padding, cell centres as in torch's
``grid_sample`` with ``align_corners=False``) and takes the element-wise maximum with
the ego's map. ``grid_sample`` writes channel-planar maps (N, C, H, W) whatever its
input's layout, so with channels-last maps (what the detector's convolutions use) the
warp, the change of layout and the maximum were three passes over every warped cell.
This loop does all three in one pass, reading each source cell's channels contiguously
(and skipping the cells whose four neighbours all lie outside the source map). With a
learned fusion gate (:class:`~roco_env.sensing.learned.network.FusionGate`) the same pass
also weighs each warped cell by the gate's two-layer perceptron on [own, theirs,
|own - theirs|] before the maximum: only on the cells a warped map reaches (elsewhere it
adds zero whatever its weight), with no window maps written and read back. Source
positions and bilinear weights are computed in float64, the weighted sums and the gate
in float32 as torch does; ``grid_sample`` computes the positions in float32, so the
warped values differ from its by up to about 5e-6 of their magnitude (2e-5 on the
shipped detector's maps, which reach about 9; tested against the torch path,
``fuse_maps``). The kernels release the GIL and write only the canvas rows of their
``band``, so :func:`~roco_env.fusion.intermediate.fuse_on_canvas` runs bands in
threads; every cell sees the maps in the same order, so the result does not depend on
the thread count.

The kernels take the maps to warp as a :class:`Warp` record and the gate's weights as a
:class:`Gate` (``typing.NamedTuple``, defined here, with every function of this module the
compiled code calls: numba's on-disk cache notices edits to a function's own file only);
from Python a record is passed as a plain tuple, ``tuple(record)``, which numba types in
C, and named again on entry.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

__all__ = ["Gate", "Warp", "warp_gate_max_into", "warp_max_into"]


class Warp(NamedTuple):
    """The maps to warp: features (N, h, w, C) float32, channels last, the source maps;
    theta (K, 2, 3): ``affine_grid`` matrices mapping normalised coordinates of a
    ``width``-column window of the canvas (all its rows) to normalised source coordinates;
    map k is source ``rows[k]`` (K,), maxed into canvas ``owner[k]`` (K,) at columns
    first[k] .. first[k] + width (first (K,))."""

    features: np.ndarray
    theta: np.ndarray
    rows: np.ndarray
    owner: np.ndarray
    first: np.ndarray
    width: int


class Gate(NamedTuple):
    """A fusion gate's per-cell weights (``FusionGate.cell_weights``): the weight of warped
    cell v beside own cell o is sigmoid(b_out + w_out . relu(b_in + [o, v, |o - v|] @
    w_in)), with w_in (3 C, hidden), b_in (hidden,), w_out (hidden,) float32 and b_out a
    float."""

    w_in: np.ndarray
    b_in: np.ndarray
    w_out: np.ndarray
    b_out: float


class _Scratch(NamedTuple):
    """The gate's work arrays for a row of cells: hidden units x cells, per cell one
    channel of the two cells and their difference, and the weights."""

    hidden: np.ndarray
    mine: np.ndarray
    theirs: np.ndarray
    difference: np.ndarray
    weights: np.ndarray


@njit(cache=True, nogil=True)
def warp_max_into(canvas, warp, band):  # pragma: no cover
    """Max each warped map of the :class:`Warp` into its ego's canvas map, in place.

    canvas (E, H, Wc, C) float32, channels last: the egos' maps (written); band (start,
    stop): the canvas rows this call writes (calls on disjoint bands may run at once in
    threads: the kernel releases the GIL).
    """
    no_vector = np.zeros(0, dtype=np.float32)
    no_gate = Gate(np.zeros((0, 0), dtype=np.float32), no_vector, no_vector, 0.0)
    _fuse(canvas, canvas, Warp(*warp), band, no_gate, False)


@njit(cache=True, nogil=True)
def warp_gate_max_into(canvas, own, warp, band, gate):  # pragma: no cover
    """:func:`warp_max_into` with every warped cell weighed by a fusion :class:`Gate`
    first.

    own (E, H, Wc, C) float32: the egos' maps before any maximum (what the gate reads;
    not ``canvas``, which is written). Every map must be non-negative (the encoder's
    maps are: ReLU), as the skipped cells assume.
    """
    _fuse(canvas, own, Warp(*warp), band, Gate(*gate), True)


@njit(cache=True, nogil=True)
def _fuse(canvas, own, warp, band, gate, gated):  # pragma: no cover
    """The loop of both kernels (their arguments, the records named); ``gated`` turns the
    gate on.

    Without the gate each warped cell is maxed in as it is sampled. With it, one canvas
    row of one map at a time: the cells the map reaches and could lift are sampled first,
    then the gate runs on all of them at once (its inner loops over the cells, which the
    compiler vectorises), then their weighted values are maxed in."""
    features, theta, rows, owner, first, width = (warp.features, warp.theta, warp.rows,
                                                  warp.owner, warp.first, warp.width)
    out_h = canvas.shape[1]
    h, w, n_ch = features.shape[1], features.shape[2], features.shape[3]
    values = np.empty((width, n_ch), dtype=np.float32)  # the row's sampled cells
    cols = np.empty(width, dtype=np.int64)
    scratch = _Scratch(np.empty((gate.b_in.shape[0], width), dtype=np.float32),
                       np.empty(width, dtype=np.float32), np.empty(width, dtype=np.float32),
                       np.empty(width, dtype=np.float32), np.empty(width, dtype=np.float32))
    weights = scratch.weights
    for k in range(theta.shape[0]):
        src = features[rows[k]]
        dst = canvas[owner[k]]
        mine = own[owner[k]]
        t = theta[k]
        # Source position in cells (cell centres at integer + 0.5, align_corners=False) of
        # output cell (i, j): normalised x_n = (2 j + 1) / width - 1, y_n = (2 i + 1) / out_h - 1,
        # mapped by t, then x = ((x_src + 1) w - 1) / 2: affine in (i, j).
        x_j, y_j = t[0, 0] * w / width, t[1, 0] * h / width
        x_i, y_i = t[0, 1] * w / out_h, t[1, 1] * h / out_h
        x_c = 0.5 * w * (t[0, 2] + 1.0 - t[0, 0] - t[0, 1]) - 0.5
        y_c = 0.5 * h * (t[1, 2] + 1.0 - t[1, 0] - t[1, 1]) - 0.5
        for i in range(band[0], band[1]):
            x_row = x_c + x_i * (i + 0.5)
            y_row = y_c + y_i * (i + 0.5)
            n = 0
            for j in range(width):
                value = values[n]
                if not _bilinear(src, x_row + x_j * (j + 0.5), y_row + y_j * (j + 0.5), value):
                    continue  # all four neighbours outside the source map: adds zero
                col = first[k] + j
                if not gated:
                    _max_into(dst[i, col], value, np.float32(1.0))
                elif not _nowhere_above(value, mine[i, col]):
                    # (else any gate weight, <= 1, leaves the maximum as it is)
                    cols[n] = col
                    n += 1
            if n:  # the gated cells of the row, weighed together
                _gate_cells(mine[i], values, cols, n, gate, scratch)
                for m in range(n):
                    _max_into(dst[i, cols[m]], values[m], weights[m])


@njit(cache=True)
def _max_into(out, value, weight):  # pragma: no cover
    """out[ch] = max(out[ch], value[ch] * weight) for every channel (value is scaled)."""
    for ch in range(out.shape[0]):
        value[ch] *= weight
        if value[ch] > out[ch]:
            out[ch] = value[ch]


@njit(cache=True)
def _nowhere_above(value, mine):  # pragma: no cover
    """Whether value[ch] <= mine[ch] for every channel."""
    for ch in range(value.shape[0]):
        if value[ch] > mine[ch]:
            return False
    return True


@njit(cache=True)
def _bilinear(src, x, y, value):  # pragma: no cover
    """Bilinear sample of src (h, w, C) at (x, y) (cells, centres at integers) into value
    (C,), zero outside; False (value untouched) when all four neighbours lie outside."""
    h, w, n_ch = src.shape
    x0, y0 = math.floor(x), math.floor(y)
    if x0 < -1.0 or x0 >= w or y0 < -1.0 or y0 >= h:
        return False
    fx, fy = x - x0, y - y0
    ix, iy = int(x0), int(y0)
    if 0 <= ix < w - 1 and 0 <= iy < h - 1:  # all four neighbours inside
        w00 = np.float32((1.0 - fy) * (1.0 - fx))
        w01 = np.float32((1.0 - fy) * fx)
        w10 = np.float32(fy * (1.0 - fx))
        w11 = np.float32(fy * fx)
        s0, s1 = src[iy], src[iy + 1]
        for ch in range(n_ch):
            value[ch] = (w00 * s0[ix, ch] + w01 * s0[ix + 1, ch]
                         + w10 * s1[ix, ch] + w11 * s1[ix + 1, ch])
        return True
    value[:] = 0.0
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
                value[ch] += weight * src[yy, xx, ch]
    return True


@njit(cache=True)
def _gate_cells(mine_row, values, cols, n, gate, scratch):  # pragma: no cover
    """The fusion :class:`Gate`'s weights, written to scratch.weights[:n], of the n cells
    values[:n] (C each) beside the ego's cells mine_row[cols[:n]]; the other
    :class:`_Scratch` arrays (hidden (H, >= n), the rest (>= n)) are work space. The same
    operations in the same order per cell as a cell at a time, but every inner loop runs
    over the cells."""
    w_in, b_in, w_out, b_out = gate.w_in, gate.b_in, gate.w_out, gate.b_out
    hidden, a, b, d, logit = (scratch.hidden, scratch.mine, scratch.theirs, scratch.difference,
                              scratch.weights)
    n_ch, n_hidden = values.shape[1], b_in.shape[0]
    for u in range(n_hidden):
        hidden[u, :n] = b_in[u]
    for ch in range(n_ch):
        for m in range(n):
            a[m] = mine_row[cols[m], ch]
            b[m] = values[m, ch]
            d[m] = abs(a[m] - b[m])
        w_a, w_b, w_d = w_in[ch], w_in[n_ch + ch], w_in[2 * n_ch + ch]
        for u in range(n_hidden):
            wa, wb, wd = w_a[u], w_b[u], w_d[u]
            row = hidden[u]
            for m in range(n):
                row[m] += a[m] * wa + b[m] * wb + d[m] * wd
    logit[:n] = np.float32(b_out)
    for u in range(n_hidden):
        wo = w_out[u]
        row = hidden[u]
        for m in range(n):
            if row[m] > 0.0:
                logit[m] += row[m] * wo
    for m in range(n):
        logit[m] = np.float32(1.0 / (1.0 + math.exp(-logit[m])))
