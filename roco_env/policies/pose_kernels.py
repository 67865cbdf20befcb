"""Compiled (numba) per-edge loops of the single-vertex pose problem.

:class:`~roco_env.policies.posegraph._PoseProblem` linearises one agent vertex against
fixed landmarks dozens of times per RoCo call, on tens to hundreds of edges. In numpy
each linearisation is ~15 array operations on (E, 3, 3) arrays whose fixed call overhead
dominates at these sizes; these loops do the same arithmetic in one pass per call
(results agree with the array formulas to rounding: tests/test_posegraph.py and the
recorded numpy-path results of tests/test_roco_reference.py).

Kernel codes: 0 = least squares, 1 = Huber, 2 = Cauchy (as
:func:`~roco_env.policies.posegraph.robust_kernel`, delta in whitened units).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["KERNEL_CODES", "damped_step", "evaluate_edges", "normal_sums"]

KERNEL_CODES = {None: 0, "huber": 1, "cauchy": 2}


@njit(cache=True)
def evaluate_edges(x, y, yaw, land_xy, t_z, angle, info, kernel, delta):
    """Residuals of E edges at the pose (x m, y m, yaw rad).

    land_xy (E, 2), t_z (E, 2): landmark centres and measurement translations; angle (E,):
    landmark yaw minus measured yaw; info (E, 3, 3): per-edge information in the rotated
    residual frame. Returns (sum of rho, chi2 (E,), u (E, 2) = R(-yaw)(t_l - t),
    Omega e (E, 3), IRLS weight (E,)).
    """
    n = land_xy.shape[0]
    c, s = math.cos(yaw), math.sin(yaw)
    chi2 = np.empty(n)
    u = np.empty((n, 2))
    info_e = np.empty((n, 3))
    weight = np.empty(n)
    d2 = delta * delta
    total = 0.0
    for k in range(n):
        dx = land_xy[k, 0] - x
        dy = land_xy[k, 1] - y
        u0 = dx * c + dy * s
        u1 = -dx * s + dy * c
        u[k, 0], u[k, 1] = u0, u1
        e0 = u0 - t_z[k, 0]
        e1 = u1 - t_z[k, 1]
        e2 = (angle[k] - yaw + math.pi) % (2.0 * math.pi) - math.pi
        for r in range(3):
            info_e[k, r] = info[k, r, 0] * e0 + info[k, r, 1] * e1 + info[k, r, 2] * e2
        q = e0 * info_e[k, 0] + e1 * info_e[k, 1] + e2 * info_e[k, 2]
        chi2[k] = q
        if kernel == 0:
            total += q
            weight[k] = 1.0
        elif kernel == 1:
            root = math.sqrt(q)
            if q <= d2:
                total += q
                weight[k] = 1.0
            else:
                total += 2.0 * delta * root - d2
                weight[k] = delta / max(root, 1e-300)
        else:
            ratio = q / d2
            total += d2 * math.log1p(ratio)
            weight[k] = 1.0 / (1.0 + ratio)
    return total, chi2, u, info_e, weight


@njit(cache=True)
def normal_sums(c, s, u, info, info_e, weight, with_gradient):
    """Gauss-Newton Hessian (3, 3) and gradient (3,) of the weighted edges (the gradient is
    zeros unless ``with_gradient``), in the (x, y, yaw) coordinates of the pose.

    With m = (-u_y, u_x): inner = sum w N^T Omega N (N = I + m e3^T), H = Q inner Q^T,
    g = -Q sum w N^T Omega e, Q = blockdiag(R(yaw), 1), c/s = cos/sin(yaw).
    """
    o = np.zeros(9)
    v0 = v1 = v2 = quad = 0.0
    g0 = g1 = g2 = 0.0
    for k in range(u.shape[0]):
        w = weight[k]
        m0, m1 = -u[k, 1], u[k, 0]
        for a in range(3):
            for b in range(3):
                o[3 * a + b] += w * info[k, a, b]
        i0 = info[k, 0, 0] * m0 + info[k, 0, 1] * m1
        i1 = info[k, 1, 0] * m0 + info[k, 1, 1] * m1
        i2 = info[k, 2, 0] * m0 + info[k, 2, 1] * m1
        v0 += w * i0
        v1 += w * i1
        v2 += w * i2
        quad += w * (m0 * i0 + m1 * i1)
        if with_gradient:
            g0 += w * info_e[k, 0]
            g1 += w * info_e[k, 1]
            g2 += w * (info_e[k, 2] + m0 * info_e[k, 0] + m1 * info_e[k, 1])
    inner = np.empty((3, 3))
    inner[0, 0], inner[0, 1], inner[0, 2] = o[0], o[1], o[2] + v0
    inner[1, 0], inner[1, 1], inner[1, 2] = o[3], o[4], o[5] + v1
    inner[2, 0], inner[2, 1], inner[2, 2] = o[6] + v0, o[7] + v1, o[8] + 2.0 * v2 + quad
    rows = np.empty((3, 3))  # inner Q^T
    for a in range(3):
        rows[a, 0] = c * inner[a, 0] - s * inner[a, 1]
        rows[a, 1] = s * inner[a, 0] + c * inner[a, 1]
        rows[a, 2] = inner[a, 2]
    hess = np.empty((3, 3))  # Q (inner Q^T)
    for b in range(3):
        hess[0, b] = c * rows[0, b] - s * rows[1, b]
        hess[1, b] = s * rows[0, b] + c * rows[1, b]
        hess[2, b] = rows[2, b]
    grad = np.zeros(3)
    if with_gradient:
        grad[0] = s * g1 - c * g0
        grad[1] = -s * g0 - c * g1
        grad[2] = -g2
    return hess, grad


@njit(cache=True)
def damped_step(hess, grad, lam, min_diag):
    """Levenberg-Marquardt step of a 3x3 system: solve (H + lam diag(max(diag H, min_diag)))
    delta = -g by Gaussian elimination with partial pivoting (as LAPACK's gesv does).
    Returns (delta (3,), max |delta_i|)."""
    a = hess.copy()
    b = -grad
    for i in range(3):
        a[i, i] += lam * max(hess[i, i], min_diag)
    for col in range(3):
        pivot = col
        for row in range(col + 1, 3):
            if abs(a[row, col]) > abs(a[pivot, col]):
                pivot = row
        if pivot != col:
            for k in range(3):
                a[col, k], a[pivot, k] = a[pivot, k], a[col, k]
            b[col], b[pivot] = b[pivot], b[col]
        if a[col, col] == 0.0:
            raise ValueError("singular LM system")
        for row in range(col + 1, 3):
            factor = a[row, col] / a[col, col]
            for k in range(col, 3):
                a[row, k] -= factor * a[col, k]
            b[row] -= factor * b[col]
    delta = np.empty(3)
    for i in range(2, -1, -1):
        acc = b[i]
        for k in range(i + 1, 3):
            acc -= a[i, k] * delta[k]
        delta[i] = acc / a[i, i]
    return delta, max(abs(delta[0]), abs(delta[1]), abs(delta[2]))
