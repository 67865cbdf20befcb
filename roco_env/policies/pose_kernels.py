"""Compiled (numba) loops of the pose-graph solvers of :mod:`roco_env.policies.posegraph`.

A RoCo call solves dozens of small problems (one agent vertex against fixed landmarks,
tens to hundreds of edges) and one joint graph; in numpy each linearisation is ~15 array
operations whose fixed call overhead dominates at these sizes. Here the per-edge
linearisation, the 3x3 LM step, the whole Levenberg-Marquardt loop of the single-vertex
problem (:func:`solve_pose`) and of the joint graph with its Schur complement
(:func:`solve_graph`) run compiled, with the array path's arithmetic and stopping rules
(tests/test_pose_kernels.py compares them with that numpy path; the recorded numpy-path
results of tests/test_roco_reference.py still hold).

RoCo's matching runs here too: the gate search (:func:`gated_pairs`), the edge similarity
(:func:`edge_similarity`; :func:`~roco_env.policies.matching._edge_similarity_from_features`
scores every candidate pair against every matched leaf; with the star graphs' neighbour
radius most (pair, leaf) combinations are not leaves of both stars, so one loop that skips
them costs a fraction of the dense (C x H) array passes, results agreeing to rounding),
the assignment's index compaction and shortcut (:func:`scored_pairs`;
tests/test_matching_kernels.py), and a collaborator's whole match-optimise loop
(:func:`attempt_rounds`; tests/test_roco_kernels.py compares it with the Python loop of
``roco._attempt_loop``). They share this module with the solver because a compiled
function calls only functions of its own module (numba's on-disk cache notices edits to
a function's own file only).

Kernel codes: 0 = least squares, 1 = Huber, 2 = Cauchy (as
:func:`~roco_env.policies.posegraph.robust_kernel`, delta in whitened units).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["KERNEL_CODES", "attempt_rounds", "compact_pairs", "damped_step", "edge_similarity",
           "edge_similarity_sums", "evaluate_edges", "gated_pairs", "inverse_covariances",
           "normal_sums", "pair_information", "placed_centres", "refine_pose", "refine_starts",
           "rotate_information",
           "scored_pairs", "solve_graph", "solve_pose", "solve_pose_edges", "wald_statistic"]

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
def rotate_information(info, meas_yaw):
    """``C^T Omega C`` (E, 3, 3) per edge, C = blockdiag(R(-yaw_z), 1): the information
    (E, 3, 3) in the rotated residual frame (meas_yaw (E,) the measured yaws, rad); the
    products summed in the order of ``C^T (Omega C)`` as matrices."""
    n = info.shape[0]
    out = np.empty((n, 3, 3))
    rot = np.zeros((3, 3))
    rot[2, 2] = 1.0
    half = np.empty((3, 3))
    for k in range(n):
        c, s = math.cos(meas_yaw[k]), math.sin(meas_yaw[k])
        rot[0, 0], rot[0, 1], rot[1, 0], rot[1, 1] = c, s, -s, c
        for a in range(3):
            for b in range(3):
                half[a, b] = info[k, a, 0] * rot[0, b] + info[k, a, 1] * rot[1, b] + (
                    info[k, a, 2] * rot[2, b]
                )
        for a in range(3):
            for b in range(3):
                out[k, a, b] = rot[0, a] * half[0, b] + rot[1, a] * half[1, b] + (
                    rot[2, a] * half[2, b]
                )
    return out


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


@njit(cache=True)
def _wrap(angle):
    """Wrap to [-pi, pi) as ``posegraph._wrap_scalar`` (Python's float ``%``)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


@njit(cache=True)
def _pose_cost(pose, land_xy, t_z, angle, info, kernel, delta, prior):
    """Robust cost and linearisation point at ``pose`` (3,): :func:`evaluate_edges` plus
    the quadratic prior edge (posegraph._PoseProblem.evaluate; a zero-information prior,
    :func:`_no_prior`, adds exact zeros). Returns (cost, chi2, u, info_e, weight, prior
    residual (3,))."""
    yaw = pose[2]
    cost, chi2, u, info_e, weight = evaluate_edges(
        pose[0], pose[1], yaw, land_xy, t_z, angle, info, kernel, delta
    )
    e_p = np.empty(3)
    j_p, offset, info_p = prior[0], prior[1], prior[2]
    for r in range(3):
        e_p[r] = j_p[r, 0] * pose[0] + j_p[r, 1] * pose[1] + j_p[r, 2] * pose[2] - offset[r]
    e_p[2] = _wrap(e_p[2])
    quad = 0.0
    for b in range(3):
        quad += (e_p[0] * info_p[0, b] + e_p[1] * info_p[1, b] + e_p[2] * info_p[2, b]) * e_p[b]
    return cost + quad, chi2, u, info_e, weight, e_p


@njit(cache=True)
def solve_pose(initial, land_xy, t_z, angle, info, kernel, delta, prior, max_iterations,
               tolerance, min_diag):
    """Levenberg-Marquardt of one agent vertex against fixed landmarks: the loop of
    :func:`solve_graph` with ``posegraph._PoseProblem``'s linearisation (same stopping
    rules, same arithmetic per edge).

    initial (3,) pose; edges as :func:`evaluate_edges`; prior: the prior edge's terms
    (:func:`prior_terms`; :func:`_no_prior` for none: its zeros change nothing). Returns
    (pose (3,), chi2 (E,) at it, initial cost, cost, iterations, converged).
    """
    x = initial.copy()
    cost, chi2, u, info_e, weight, e_p = _pose_cost(
        x, land_xy, t_z, angle, info, kernel, delta, prior
    )
    initial_cost, lam, iterations, converged = cost, 1e-4, 0, False
    while iterations < max_iterations and not converged:
        iterations += 1
        hess, grad = normal_sums(
            math.cos(x[2]), math.sin(x[2]), u, info, info_e, weight, True
        )
        hess += prior[3]
        for r in range(3):
            grad[r] += prior[4][0, r] * e_p[0] + prior[4][1, r] * e_p[1] + prior[4][2, r] * e_p[2]
        while True:
            step_delta, step = damped_step(hess, grad, lam, min_diag)
            trial = x + step_delta
            trial[2] = _wrap(trial[2])
            t_cost, t_chi2, t_u, t_info_e, t_weight, t_e_p = _pose_cost(
                trial, land_xy, t_z, angle, info, kernel, delta, prior
            )
            if t_cost <= cost:
                break
            lam *= 10.0
            if lam > 1e12:
                converged = True  # no damping reduces the cost: a (local) minimum
                break
        if converged:
            break
        decrease = cost - t_cost
        x, cost = trial, t_cost
        chi2, u, info_e, weight, e_p = t_chi2, t_u, t_info_e, t_weight, t_e_p
        lam = max(lam / 10.0, 1e-12)
        converged = decrease <= tolerance * max(cost, 1e-300) or step <= tolerance
    return x, chi2, initial_cost, cost, iterations, converged


@njit(cache=True)
def _graph_cost(x, n_agents, from_v, to_v, meas_yaw, meas_offset, info, n_obs, kernel, delta):
    """Robust cost of the pose graph at the vertices x (V, 3) (agents, then landmarks) and
    per edge: e (E, 3), chi2 (E,), IRLS weight (E,; 1 on prior edges), and the Jacobian
    terms c, s, w_x, w_y (E,) of ``Z^{-1} T_a^{-1} T_b`` (``posegraph._residuals``)."""
    n = from_v.size
    e = np.empty((n, 3))
    chi2 = np.empty(n)
    weight = np.ones(n)
    terms = np.empty((n, 4))
    d2 = delta * delta
    rho_sum = 0.0
    prior_sum = 0.0
    for k in range(n):
        a = from_v[k]
        b = to_v[k] if k >= n_obs else n_agents + to_v[k]
        angle = x[a, 2] + meas_yaw[k]
        c, s = math.cos(angle), math.sin(angle)
        dx, dy = x[b, 0] - x[a, 0], x[b, 1] - x[a, 1]
        wx, wy = c * dx + s * dy, -s * dx + c * dy
        e0, e1, e2 = wx - meas_offset[k, 0], wy - meas_offset[k, 1], _wrap(x[b, 2] - angle)
        e[k, 0], e[k, 1], e[k, 2] = e0, e1, e2
        terms[k, 0], terms[k, 1], terms[k, 2], terms[k, 3] = c, s, wx, wy
        q = 0.0
        for r in range(3):
            q += e[k, r] * (info[k, r, 0] * e0 + info[k, r, 1] * e1 + info[k, r, 2] * e2)
        chi2[k] = q
        if k >= n_obs:
            prior_sum += q
        elif kernel == 0:
            rho_sum += q
        elif kernel == 1:
            root = math.sqrt(q)
            if q <= d2:
                rho_sum += q
            else:
                rho_sum += 2.0 * delta * root - d2
                weight[k] = delta / max(root, 1e-300)
        else:
            ratio = q / d2
            rho_sum += d2 * math.log1p(ratio)
            weight[k] = 1.0 / (1.0 + ratio)
    return rho_sum + prior_sum, e, chi2, weight, terms


@njit(cache=True)
def _graph_normal_equations(n_agents, n_land, from_v, to_v, info, n_obs, e, weight, terms):
    """H_aa (3N, 3N), H_al (3N, 3M), block-diagonal H_ll (M, 3, 3), g_a (3N,), g_l (M, 3)
    of the weighted edges: each edge adds J^T w Omega J and J^T w Omega e, J = [J_a | J_b]
    (3, 6) its Jacobian; rows/columns 3-5 belong to the landmark (observation edges) or
    to the second agent (prior edges)."""
    h_aa = np.zeros((3 * n_agents, 3 * n_agents))
    h_al = np.zeros((3 * n_agents, 3 * n_land))
    h_ll = np.zeros((n_land, 3, 3))
    g_a = np.zeros(3 * n_agents)
    g_l = np.zeros((n_land, 3))
    jac = np.zeros((3, 6))
    jac[2, 2], jac[2, 5] = -1.0, 1.0
    jt_info = np.empty((6, 3))
    block = np.empty((6, 6))
    grad = np.empty(6)
    for k in range(from_v.size):
        c, s, wx, wy = terms[k, 0], terms[k, 1], terms[k, 2], terms[k, 3]
        jac[0, 0], jac[0, 1], jac[0, 2], jac[0, 3], jac[0, 4] = -c, -s, wy, c, s
        jac[1, 0], jac[1, 1], jac[1, 2], jac[1, 3], jac[1, 4] = s, -c, -wx, -s, c
        w = weight[k]
        for i in range(6):
            for r in range(3):
                jt_info[i, r] = (
                    jac[0, i] * info[k, 0, r] + jac[1, i] * info[k, 1, r] + jac[2, i] * info[k, 2, r]
                ) * w
        for i in range(6):
            for j in range(6):
                block[i, j] = jt_info[i, 0] * jac[0, j] + jt_info[i, 1] * jac[1, j] + (
                    jt_info[i, 2] * jac[2, j]
                )
            grad[i] = jt_info[i, 0] * e[k, 0] + jt_info[i, 1] * e[k, 1] + jt_info[i, 2] * e[k, 2]
        a = 3 * from_v[k]
        if k < n_obs:
            land = to_v[k]
            for i in range(3):
                g_a[a + i] += grad[i]
                g_l[land, i] += grad[3 + i]
                for j in range(3):
                    h_aa[a + i, a + j] += block[i, j]
                    h_al[a + i, 3 * land + j] += block[i, 3 + j]
                    h_ll[land, i, j] += block[3 + i, 3 + j]
        else:
            b = 3 * to_v[k]
            for i in range(3):
                g_a[a + i] += grad[i]
                g_a[b + i] += grad[3 + i]
                for j in range(3):
                    h_aa[a + i, a + j] += block[i, j]
                    h_aa[a + i, b + j] += block[i, 3 + j]
                    h_aa[b + i, a + j] += block[3 + i, j]
                    h_aa[b + i, b + j] += block[3 + i, 3 + j]
    return h_aa, h_al, h_ll, g_a, g_l


@njit(cache=True)
def _inverse3(a, out):
    """Inverse of the 3x3 matrix ``a`` into ``out`` (adjugate over determinant; ``a`` is
    a damped landmark block, symmetric positive definite)."""
    c00 = a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1]
    c01 = a[1, 2] * a[2, 0] - a[1, 0] * a[2, 2]
    c02 = a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]
    det = a[0, 0] * c00 + a[0, 1] * c01 + a[0, 2] * c02
    if det == 0.0:
        raise ValueError("singular landmark block")
    inv = 1.0 / det
    out[0, 0], out[1, 0], out[2, 0] = c00 * inv, c01 * inv, c02 * inv
    out[0, 1] = (a[0, 2] * a[2, 1] - a[0, 1] * a[2, 2]) * inv
    out[1, 1] = (a[0, 0] * a[2, 2] - a[0, 2] * a[2, 0]) * inv
    out[2, 1] = (a[0, 1] * a[2, 0] - a[0, 0] * a[2, 1]) * inv
    out[0, 2] = (a[0, 1] * a[1, 2] - a[0, 2] * a[1, 1]) * inv
    out[1, 2] = (a[0, 2] * a[1, 0] - a[0, 0] * a[1, 2]) * inv
    out[2, 2] = (a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]) * inv


@njit(cache=True)
def _graph_step(h_aa, h_al, h_ll, g_a, g_l, rows, row_start, free, lam, min_diag):
    """LM step (d_agents (3N,), d_landmarks (M, 3), max |component|) with Marquardt
    damping ``lam``; the landmarks are eliminated by the Schur complement and the agents
    not in ``free`` (coordinate indices) stay fixed. H_al's block column of landmark m is
    zero outside the coordinate rows ``rows[row_start[m]:row_start[m + 1]]`` (those of
    the agents observing it), so only those rows are visited."""
    n_a, n_land = h_aa.shape[0], h_ll.shape[0]
    damped = h_aa.copy()
    for i in range(n_a):
        damped[i, i] += lam * max(h_aa[i, i], min_diag)
    rhs = -g_a
    h_ll_inv = np.empty((n_land, 3, 3))
    y = np.empty((n_a, 3))
    h_ll_d = np.empty((3, 3))
    al = np.empty((n_a, 3))  # the nonzero rows of H_al's block column, gathered
    for m in range(n_land):
        h_ll_d[:] = h_ll[m]
        for i in range(3):
            h_ll_d[i, i] += lam * max(h_ll[m, i, i], min_diag)
        _inverse3(h_ll_d, h_ll_inv[m])
        col = 3 * m
        seen = rows[row_start[m] : row_start[m + 1]]
        k = seen.size
        for a in range(k):
            al[a, 0], al[a, 1], al[a, 2] = h_al[seen[a], col], h_al[seen[a], col + 1], h_al[
                seen[a], col + 2
            ]
        for a in range(k):  # Y = H_al,m H_ll,m^{-1}
            for j in range(3):
                y[a, j] = al[a, 0] * h_ll_inv[m, 0, j] + al[a, 1] * h_ll_inv[m, 1, j] + (
                    al[a, 2] * h_ll_inv[m, 2, j]
                )
        for a in range(k):
            # Y H_al^T is symmetric: one triangle, mirrored (row a's factors held in locals:
            # the writes into ``damped`` would otherwise reload them).
            r = seen[a]
            ya0, ya1, ya2 = y[a, 0], y[a, 1], y[a, 2]
            damped[r, r] -= ya0 * al[a, 0] + ya1 * al[a, 1] + ya2 * al[a, 2]
            for b in range(a + 1, k):
                c = seen[b]
                update = ya0 * al[b, 0] + ya1 * al[b, 1] + ya2 * al[b, 2]
                damped[r, c] -= update
                damped[c, r] -= update
            rhs[r] += y[a, 0] * g_l[m, 0] + y[a, 1] * g_l[m, 1] + y[a, 2] * g_l[m, 2]
    d_a = np.zeros(n_a)
    if free.size:
        reduced = np.empty((free.size, free.size))
        for i in range(free.size):
            for j in range(free.size):
                reduced[i, j] = damped[free[i], free[j]]
        solved = np.linalg.solve(reduced, rhs[free])
        for i in range(free.size):
            d_a[free[i]] = solved[i]
    step = 0.0
    for i in range(n_a):
        step = max(step, abs(d_a[i]))
    d_l = np.empty((n_land, 3))
    v = np.empty(3)
    for m in range(n_land):
        for j in range(3):
            back = 0.0
            for r in rows[row_start[m] : row_start[m + 1]]:
                back += h_al[r, 3 * m + j] * d_a[r]
            v[j] = g_l[m, j] + back
        for i in range(3):
            d_l[m, i] = -(
                h_ll_inv[m, i, 0] * v[0] + h_ll_inv[m, i, 1] * v[1] + h_ll_inv[m, i, 2] * v[2]
            )
            step = max(step, abs(d_l[m, i]))
    return d_a, d_l, step


@njit(cache=True)
def _landmark_rows(n_agents, n_land, from_v, to_v, n_obs):
    """Per landmark, the coordinate rows (3 per agent, agents in increasing order) of the
    agents observing it, as CSR (rows, start (M + 1,))."""
    sees = np.zeros((n_land, n_agents), dtype=np.bool_)
    for k in range(n_obs):
        sees[to_v[k], from_v[k]] = True
    start = np.zeros(n_land + 1, dtype=np.int64)
    for m in range(n_land):
        start[m + 1] = start[m] + 3 * sees[m].sum()
    rows = np.empty(start[n_land], dtype=np.int64)
    for m in range(n_land):
        k = start[m]
        for a in range(n_agents):
            if sees[m, a]:
                rows[k], rows[k + 1], rows[k + 2] = 3 * a, 3 * a + 1, 3 * a + 2
                k += 3
    return rows, start


@njit(cache=True)
def solve_graph(x0, n_agents, from_v, to_v, meas_yaw, meas_offset, info, n_obs, free, kernel,
                delta, max_iterations, tolerance, min_diag):
    """Levenberg-Marquardt on a pose graph (``posegraph.optimize``): vertices x0 (V, 3),
    agents first then landmarks; E edges, the first ``n_obs`` observations (agent
    ``from_v`` -> landmark ``to_v``, a landmark index), then priors (agent -> agent);
    measurement yaw (E,), R_z^T t_z (E, 2), information (E, 3, 3); ``free``: coordinate
    indices of the agents that move. Starts with lam = 1e-4; an accepted step (cost not
    raised) divides lam by 10, a rejected one multiplies it by 10 until 1e12 (no
    progress: converged); stops after ``max_iterations`` linearisations, or when an
    accepted step's relative cost decrease or largest component is below ``tolerance``.
    Returns (x (V, 3), chi2 (E,), initial cost, cost, iterations, converged)."""
    n_land = x0.shape[0] - n_agents
    rows, row_start = _landmark_rows(n_agents, n_land, from_v, to_v, n_obs)
    x = x0.copy()
    cost, e, chi2, weight, terms = _graph_cost(
        x, n_agents, from_v, to_v, meas_yaw, meas_offset, info, n_obs, kernel, delta
    )
    initial_cost, lam, iterations, converged = cost, 1e-4, 0, False
    while iterations < max_iterations and not converged:
        iterations += 1
        h_aa, h_al, h_ll, g_a, g_l = _graph_normal_equations(
            n_agents, n_land, from_v, to_v, info, n_obs, e, weight, terms
        )
        while True:
            d_a, d_l, step = _graph_step(
                h_aa, h_al, h_ll, g_a, g_l, rows, row_start, free, lam, min_diag
            )
            trial = x.copy()
            for v in range(x.shape[0]):
                for i in range(3):
                    trial[v, i] += d_a[3 * v + i] if v < n_agents else d_l[v - n_agents, i]
                trial[v, 2] = _wrap(trial[v, 2])
            t_cost, t_e, t_chi2, t_weight, t_terms = _graph_cost(
                trial, n_agents, from_v, to_v, meas_yaw, meas_offset, info, n_obs, kernel, delta
            )
            if t_cost <= cost:
                break
            lam *= 10.0
            if lam > 1e12:
                converged = True  # no damping reduces the cost: a (local) minimum
                break
        if converged:
            break
        decrease = cost - t_cost
        x, cost, e, chi2, weight, terms = trial, t_cost, t_e, t_chi2, t_weight, t_terms
        lam = max(lam / 10.0, 1e-12)
        converged = decrease <= tolerance * max(cost, 1e-300) or step <= tolerance
    return x, chi2, initial_cost, cost, iterations, converged


@njit(cache=True)
def inverse_covariances(covariance):
    """Information (E, 3, 3): the inverse of each covariance (E, 3, 3) (symmetric positive
    definite), matrix by matrix (:func:`_inverse3`)."""
    info = np.empty(covariance.shape)
    for k in range(covariance.shape[0]):
        _inverse3(covariance[k], info[k])
    return info


@njit(cache=True)
def wald_statistic(start, landmarks, own, covariance, reported, kernel, delta, max_iterations,
                   tolerance, min_diag):
    """Robust Wald statistic of a correction (RoCo's significance test).

    The agent pose is fitted from ``start`` (3,) to its P edges alone (no prior): fixed
    landmarks (P, 3), its boxes ``own`` (P, 3) in its frame, each edge with the
    information ``covariance^-1`` (covariance (P, 3, 3) in the box frame), the robust
    kernel and the LM rules of :func:`solve_pose`; then ``d = fit - reported`` (yaw
    wrapped) is weighed by the sandwich ``A^-1 B A^-1``, A = sum w J^T Omega J,
    B = sum w^2 J^T Omega J with w the IRLS weights at the fit: returns ``d^T A B^-1 A d``.
    """
    info = rotate_information(inverse_covariances(covariance), np.ascontiguousarray(own[:, 2]))
    land_xy = np.ascontiguousarray(landmarks[:, :2])
    t_z = np.ascontiguousarray(own[:, :2])
    angle = landmarks[:, 2] - own[:, 2]
    pose = solve_pose(start, land_xy, t_z, angle, info, kernel, delta, _no_prior(), max_iterations,
                      tolerance, min_diag)[0]
    _, _, u, info_e, weight = evaluate_edges(
        pose[0], pose[1], pose[2], land_xy, t_z, angle, info, kernel, delta
    )
    c, s = math.cos(pose[2]), math.sin(pose[2])
    bread = normal_sums(c, s, u, info, info_e, weight, False)[0]
    meat = normal_sums(c, s, u, info, info_e, weight * weight, False)[0]
    d = pose - reported
    d[2] = _wrap(d[2])
    ad = bread @ d
    solved = damped_step(meat, -ad, 0.0, min_diag)[0]  # B^-1 A d
    return ad[0] * solved[0] + ad[1] * solved[1] + ad[2] * solved[2]


@njit(cache=True)
def refine_pose(initial, land_poses, own_poses, own_info, gate, kernel, delta, min_matches,
                max_iterations, tolerance, min_diag):
    """Up to two rounds of nearest-centre matching and a robust single-vertex solve (the
    refinement of roco_antialias's hypotheses, :func:`refine_starts`).

    Each round maps the agent's boxes own_poses (K, 3) (its frame) into the landmarks'
    frame with the current pose (initial (3,) first), pairs every box with its nearest
    landmark (land_poses (L, 3); lowest index among equal distances) closer than
    ``gate`` m, and solves the pose from those pairs (boxes' information own_info (K, 3, 3),
    no prior; LM rules of :func:`solve_pose`). The second round runs only when the pairs
    changed. Returns (pose (3,), True), or (initial, False) when fewer than
    ``min_matches`` boxes match in a round.
    """
    by_x = np.argsort(land_poses[:, 0])
    return _refine_sorted(initial, land_poses, by_x, land_poses[by_x, 0], own_poses, own_info,
                          gate, kernel, delta, min_matches, max_iterations, tolerance, min_diag)


@njit(cache=True)
def _refine_sorted(initial, land_poses, by_x, sorted_x, own_poses, own_info, gate, kernel,
                   delta, min_matches, max_iterations, tolerance, min_diag):
    """:func:`refine_pose` with the landmarks' order by x (by_x (L,)) and their sorted x
    (L,) given: only landmarks within the gate in x (with a margin far above rounding) can
    be nearer than the gate; ties go to the lowest index, as in a scan."""
    pose = initial.copy()
    n_own, n_land = own_poses.shape[0], land_poses.shape[0]
    if min(n_own, n_land) < min_matches:
        return pose, False
    previous = np.full(n_own, -2, dtype=np.int64)
    nearest = np.empty(n_own, dtype=np.int64)
    for _ in range(2):
        c, s = math.cos(pose[2]), math.sin(pose[2])
        count = 0
        for q in range(n_own):
            x = c * own_poses[q, 0] - s * own_poses[q, 1] + pose[0]
            y = s * own_poses[q, 0] + c * own_poses[q, 1] + pose[1]
            nearest[q] = _nearest(x, y, land_poses, by_x, sorted_x, gate)
            count += nearest[q] >= 0
        if count < min_matches:
            return initial.copy(), False
        if np.array_equal(nearest, previous):
            break
        previous[:] = nearest
        box = np.nonzero(nearest >= 0)[0]
        land = nearest[box]
        own = own_poses[box]
        landmarks = land_poses[land]
        info = rotate_information(np.ascontiguousarray(own_info[box]), np.ascontiguousarray(own[:, 2]))
        pose = solve_pose(pose, np.ascontiguousarray(landmarks[:, :2]),
                          np.ascontiguousarray(own[:, :2]), landmarks[:, 2] - own[:, 2], info,
                          kernel, delta, _no_prior(), max_iterations, tolerance, min_diag)[0]
    return pose, True


@njit(cache=True)
def _nearest(x, y, land_poses, by_x, sorted_x, gate):
    """The landmark (index into land_poses (L, 3)) nearest the centre (x, y) and closer than
    ``gate`` m, the lowest index among equal distances; -1 when none is. by_x (L,): the
    landmarks' order by x, sorted_x (L,) their sorted x: only those within the gate in x
    (with a margin far above rounding) are measured."""
    reach = gate * (1.0 + 1e-6)
    best, best_p = gate, -1
    for k in range(np.searchsorted(sorted_x, x - reach), land_poses.shape[0]):
        if sorted_x[k] > x + reach:
            break
        p = by_x[k]
        d = math.sqrt((land_poses[p, 0] - x) ** 2 + (land_poses[p, 1] - y) ** 2)
        if d < best or (d == best and 0 <= p < best_p):
            best, best_p = d, p
    return best_p


@njit(cache=True)
def pair_information(land_poses, land_var_t, land_var_r, own_poses, own_var_t, own_var_r, pose,
                     gate, slack_t, slack_r):
    """Information (3, 3) of the agent's pose (3,) (x m, y m, yaw rad) from the pairs of each
    of its boxes (own_poses (K, 3) in its frame, mapped by ``pose``) with the nearest
    landmark (land_poses (L, 3)) closer than ``gate`` m, as the refinement pairs them, and
    the number of pairs (the ambiguity diagnosis, ``roco_env.policies.ambiguity``, step 1).

    A pair's position residual has variance ``land_var_t + own_var_t + slack_t`` (m^2) in x
    and y, its heading residual ``land_var_r + own_var_r + slack_r`` (rad^2); the mapped
    centre's derivative in yaw is its offset from the agent's origin turned by 90 degrees."""
    info = np.zeros((3, 3))
    if land_poses.shape[0] == 0:
        return info, 0
    by_x = np.argsort(land_poses[:, 0])
    sorted_x = land_poses[by_x, 0]
    c, s = math.cos(pose[2]), math.sin(pose[2])
    count = 0
    for q in range(own_poses.shape[0]):
        x = c * own_poses[q, 0] - s * own_poses[q, 1] + pose[0]
        y = s * own_poses[q, 0] + c * own_poses[q, 1] + pose[1]
        p = _nearest(x, y, land_poses, by_x, sorted_x, gate)
        if p < 0:
            continue
        w_t = 1.0 / (land_var_t[p] + own_var_t[q] + slack_t)
        w_r = 1.0 / (land_var_r[p] + own_var_r[q] + slack_r)
        lever_x, lever_y = -(y - pose[1]), x - pose[0]
        info[0, 0] += w_t
        info[0, 2] += w_t * lever_x
        info[1, 2] += w_t * lever_y
        info[2, 2] += w_t * (lever_x * lever_x + lever_y * lever_y) + w_r
        count += 1
    info[1, 1] = info[0, 0]
    info[2, 0], info[2, 1] = info[0, 2], info[1, 2]
    return info, count


@njit(cache=True)
def _close(a, b, tolerance):
    """Poses (3,) within ``tolerance`` m and ``tolerance`` deg of each other (translation
    by the C library's hypot, as np.hypot; the yaw difference wrapped to [-pi, pi))."""
    yaw = (a[2] - b[2] + math.pi) % (2.0 * math.pi) - math.pi
    return math.hypot(a[0] - b[0], a[1] - b[1]) <= tolerance and (
        math.degrees(abs(yaw)) <= tolerance
    )


@njit(cache=True)
def refine_starts(peaks, seeds, land_poses, own_poses, own_info, gate, kernel, delta,
                  min_matches, max_iterations, tolerance, min_diag):
    """The refined hypotheses (R, 3) of one collaborator (``roco_env.policies.antialias``,
    step 1): the vote peaks (H, 3), then each seed (S, 3) (the reported pose, a track's
    prediction) unless within 0.5 m / 0.5 deg of a peak (it would refine to the same
    pose), refined in turn by :func:`refine_pose` (arguments as there); a start matching
    too few boxes, or refining to within 0.3 m / 0.3 deg of an earlier result, adds none."""
    n_peaks = peaks.shape[0]
    starts = np.empty((n_peaks + seeds.shape[0], 3))
    starts[:n_peaks] = peaks
    n_starts = n_peaks
    for k in range(seeds.shape[0]):
        near = False
        for h in range(n_peaks):
            near = near or _close(seeds[k], peaks[h], 0.5)
        if not near:
            starts[n_starts] = seeds[k]
            n_starts += 1
    by_x = np.argsort(land_poses[:, 0])
    sorted_x = land_poses[by_x, 0]
    refined = np.empty((n_starts, 3))
    count = 0
    for k in range(n_starts):
        pose, ok = _refine_sorted(starts[k], land_poses, by_x, sorted_x, own_poses, own_info,
                                  gate, kernel, delta, min_matches, max_iterations, tolerance,
                                  min_diag)
        if not ok:
            continue
        duplicate = False
        for other in range(count):
            duplicate = duplicate or _close(pose, refined[other], 0.3)
        if not duplicate:
            refined[count] = pose
            count += 1
    return refined[:count].copy()


@njit(cache=True)
def prior_terms(z, info_p):
    """Constant terms of the prior edge identity -> agent measuring z (3,) with
    information info_p (3, 3): (J_p, J_p z, Omega_p, J_p^T Omega_p J_p, Omega_p J_p), with
    the edge's constant Jacobian J_p = blockdiag(R_z^T, 1); its residual is
    J_p pose - J_p z, yaw wrapped."""
    cz, sz = math.cos(z[2]), math.sin(z[2])
    j_p = np.zeros((3, 3))
    j_p[0, 0], j_p[0, 1], j_p[1, 0], j_p[1, 1], j_p[2, 2] = cz, sz, -sz, cz, 1.0
    offset = np.empty(3)
    ip_jp = np.empty((3, 3))  # Omega_p J_p
    jt_ip = np.empty((3, 3))  # J_p^T Omega_p
    for a in range(3):
        offset[a] = j_p[a, 0] * z[0] + j_p[a, 1] * z[1] + j_p[a, 2] * z[2]
        for b in range(3):
            ip_jp[a, b] = info_p[a, 0] * j_p[0, b] + info_p[a, 1] * j_p[1, b] + (
                info_p[a, 2] * j_p[2, b]
            )
            jt_ip[a, b] = j_p[0, a] * info_p[0, b] + j_p[1, a] * info_p[1, b] + (
                j_p[2, a] * info_p[2, b]
            )
    hess = np.empty((3, 3))
    for a in range(3):
        for b in range(3):
            hess[a, b] = jt_ip[a, 0] * j_p[0, b] + jt_ip[a, 1] * j_p[1, b] + jt_ip[a, 2] * j_p[2, b]
    return j_p, offset, info_p.copy(), hess, ip_jp


@njit(cache=True)
def _no_prior():
    """:func:`prior_terms` of a prior edge with zero information (no prior)."""
    return prior_terms(np.zeros(3), np.zeros((3, 3)))


@njit(cache=True)
def solve_pose_edges(initial, landmarks, measurement, information, prior_z, prior_info, kernel,
                     delta, max_iterations, tolerance, min_diag):
    """:func:`solve_pose` from the edges as given: landmarks (E, 3), measurements (E, 3)
    (the landmarks in the agent's frame), information (E, 3, 3), and the prior edge's
    measurement prior_z (3,) and information prior_info (3, 3) (zeros: no prior); the
    per-edge terms and the prior's (:func:`prior_terms`) are built here."""
    land_xy = np.ascontiguousarray(landmarks[:, :2])
    t_z = np.ascontiguousarray(measurement[:, :2])
    angle = landmarks[:, 2] - measurement[:, 2]
    info = rotate_information(np.ascontiguousarray(information),
                              np.ascontiguousarray(measurement[:, 2]))
    return solve_pose(initial, land_xy, t_z, angle, info, kernel, delta,
                      prior_terms(prior_z, prior_info), max_iterations, tolerance, min_diag)


@njit(cache=True)
def edge_similarity_sums(cand, leaf, cand_p, cand_q, leaves, partner, centres, radius2):
    """S_edge (C,): mean over usable leaves h of exp(-sqrt(max(cand[c] . leaf[:, h], 0))).

    cand (C, 11) / leaf (11, H): the bilinear factors of ||T_pm T_qn^{-1} - I||_F^2;
    a leaf is usable for candidate c when it is neither p nor q's partner, and (radius2
    >= 0) both centre offsets are within the radius: centres (C, 4) = (p_x, p_y, q_x,
    q_y) and leaf rows 11-14 of ``leaf`` hold (m_x, m_y, n_x, n_y). 0 without a usable leaf.
    """
    n_cand, n_leaf = cand.shape[0], leaf.shape[1]
    out = np.empty(n_cand)
    for c in range(n_cand):
        total = 0.0
        count = 0
        for h in range(n_leaf):
            if leaves[h] == cand_p[c] or partner[h] == cand_q[c]:
                continue
            if radius2 >= 0.0:
                dx, dy = centres[c, 0] - leaf[11, h], centres[c, 1] - leaf[12, h]
                if dx * dx + dy * dy > radius2:
                    continue
                dx, dy = centres[c, 2] - leaf[13, h], centres[c, 3] - leaf[14, h]
                if dx * dx + dy * dy > radius2:
                    continue
            norm2 = 0.0
            for i in range(11):
                norm2 += cand[c, i] * leaf[i, h]
            total += math.exp(-math.sqrt(max(norm2, 0.0)))
            count += 1
        out[c] = total / max(count, 1)
    return out


@njit(cache=True)
def edge_similarity(land, box, cand_p, cand_q, leaves, partner, radius2):
    """S_edge (C,) of the candidate pairs (cand_p landmark, cand_q box) given the initial
    matches (leaves (H,) landmarks m, partner (H,) their boxes n = A(m)), from the pose
    features (5, L) / (5, K) (x, y, x^2 + y^2, cos yaw, sin yaw) of the landmarks and the
    boxes: the (C, 11) candidate and (11, H) leaf factors of
    ``matching._edge_similarity_from_features`` (the same arithmetic element by element),
    summed by :func:`edge_similarity_sums`; radius2 < 0: no neighbour radius."""
    n_cand, h = cand_p.size, leaves.size
    cand = np.empty((n_cand, 11))
    centres = np.empty((n_cand, 4))
    for c in range(n_cand):
        p, q = cand_p[c], cand_q[c]
        px, py, p2, pc, ps = land[0, p], land[1, p], land[2, p], land[3, p], land[4, p]
        qx, qy, q2, qc, qs = box[0, q], box[1, q], box[2, q], box[3, q], box[4, q]
        cand[c, 0] = 1.0
        cand[c, 1] = pc * qc + ps * qs  # cos(v)
        cand[c, 2] = ps * qc - pc * qs  # sin(v)
        cand[c, 3], cand[c, 4], cand[c, 5] = px, py, p2
        cand[c, 6], cand[c, 7], cand[c, 8] = qx, qy, q2
        cand[c, 9] = px * qx + py * qy
        cand[c, 10] = py * qx - px * qy
        centres[c, 0], centres[c, 1], centres[c, 2], centres[c, 3] = px, py, qx, qy
    leaf = np.zeros((15, h))  # rows 11-14: leaf centres for the radius test
    for k in range(h):
        m, n = leaves[k], partner[k]
        mx, my, m2, mc, ms = land[0, m], land[1, m], land[2, m], land[3, m], land[4, m]
        nx, ny, n2, nc, ns = box[0, n], box[1, n], box[2, n], box[3, n], box[4, n]
        cu, su = mc * nc + ms * ns, ms * nc - mc * ns  # cos, sin of u = yaw_m - yaw_n
        rot_n_x, rot_n_y = cu * nx - su * ny, su * nx + cu * ny  # R(u) t_n
        rot_m_x, rot_m_y = mx * cu + my * su, my * cu - mx * su  # R(u)^T t_m
        leaf[0, k] = 4.0 + m2 + n2 - 2.0 * (mx * rot_n_x + my * rot_n_y)
        leaf[1, k], leaf[2, k] = -4.0 * cu, -4.0 * su
        leaf[3, k], leaf[4, k] = 2.0 * (rot_n_x - mx), 2.0 * (rot_n_y - my)
        leaf[6, k], leaf[7, k] = 2.0 * (rot_m_x - nx), 2.0 * (rot_m_y - ny)
        leaf[5, k] = leaf[8, k] = 1.0
        leaf[9, k], leaf[10, k] = -2.0 * cu, -2.0 * su
        leaf[11, k], leaf[12, k], leaf[13, k], leaf[14, k] = mx, my, nx, ny
    return edge_similarity_sums(cand, leaf, cand_p, cand_q, leaves, partner, centres, radius2)


@njit(cache=True)
def gated_pairs(land_xy, centres, tau2):
    """Candidate pairs of the gate and the initial matches, without (L x K) temporaries.

    land_xy (L, 2), centres (K, 2) in the ego frame; distance = sqrt(dx^2 + dy^2).
    Returns (p (C,), q (C,), distance (C,)) of the pairs with distance <= tau2 in row-major
    (p, then q) order, and (leaves (H,), partner (H,)): every landmark whose nearest box
    (lowest index among equal distances) is within the gate, with that box. A pair whose
    |dx| or |dy| alone exceeds the gate (by more than rounding) is skipped unmeasured; the
    boxes are sorted by x once, so each landmark scans only its window in x.
    """
    n_land, n_box = land_xy.shape[0], centres.shape[0]
    reach = tau2 * (1.0 + 1e-12)
    window = tau2 * (1.0 + 1e-6)  # holds every box within reach in x
    by_x = np.argsort(centres[:, 0])
    sorted_x = centres[by_x, 0]
    cand_p = np.empty(max(4 * n_land, 16), dtype=np.int64)
    cand_q = np.empty_like(cand_p)
    dis = np.empty(cand_p.size)
    leaves = np.empty(n_land, dtype=np.int64)
    partner = np.empty(n_land, dtype=np.int64)
    row_q = np.empty(n_box, dtype=np.int64)
    row_d = np.empty(n_box)
    k = h = 0
    for p in range(n_land):
        lx, ly = land_xy[p, 0], land_xy[p, 1]
        best, best_q, size = math.inf, -1, 0
        for w in range(np.searchsorted(sorted_x, lx - window), n_box):
            if sorted_x[w] > lx + window:
                break
            q = by_x[w]
            dx = lx - centres[q, 0]
            dy = ly - centres[q, 1]
            if abs(dx) > reach or abs(dy) > reach:
                continue  # beyond the gate: neither a pair nor a nearest box within it
            d = math.sqrt(dx * dx + dy * dy)
            if d <= tau2:  # the row's pairs, kept in increasing box order
                slot = size
                while slot and row_q[slot - 1] > q:
                    row_q[slot], row_d[slot] = row_q[slot - 1], row_d[slot - 1]
                    slot -= 1
                row_q[slot], row_d[slot] = q, d
                size += 1
            if d < best or (d == best and q < best_q):
                best, best_q = d, q
        if k + size > cand_p.size:
            grown = max(2 * cand_p.size, k + size)
            cand_p = np.concatenate((cand_p, np.empty(grown - cand_p.size, dtype=np.int64)))
            cand_q = np.concatenate((cand_q, np.empty(grown - cand_q.size, dtype=np.int64)))
            dis = np.concatenate((dis, np.empty(grown - dis.size)))
        for r in range(size):
            cand_p[k], cand_q[k], dis[k] = p, row_q[r], row_d[r]
            k += 1
        if best <= tau2:
            leaves[h], partner[h] = p, best_q
            h += 1
    return cand_p[:k].copy(), cand_q[:k].copy(), dis[:k].copy(), leaves[:h], partner[:h]


@njit(cache=True)
def _compact_axis(index):
    """The distinct values of ``index`` (C,) (non-negative), sorted, the position of each
    entry's value among them (C,), and whether every value occurs once."""
    size = 0
    for k in range(index.size):
        size = max(size, index[k] + 1)
    count = np.zeros(size, dtype=np.int64)
    for k in range(index.size):
        count[index[k]] += 1
    single = True
    position = np.empty(size, dtype=np.int64)
    n_used = 0
    for i in range(size):
        position[i] = n_used
        if count[i]:
            n_used += 1
            single = single and count[i] == 1
    used = np.empty(n_used, dtype=np.int64)
    for i in range(size):
        if count[i]:
            used[position[i]] = i
    inverse = np.empty(index.size, dtype=np.int64)
    for k in range(index.size):
        inverse[k] = position[index[k]]
    return used, inverse, single


@njit(cache=True)
def compact_pairs(cand_p, cand_q):
    """The rows and columns the candidate pairs (C,) use (non-negative indices), as
    ``np.unique`` with ``return_inverse`` gives them: (rows (R,) sorted, row index of each
    pair (C,), cols (Q,) sorted, column index of each pair (C,)), and whether every row
    and every column has a single pair."""
    rows, row_idx, single_rows = _compact_axis(cand_p)
    cols, col_idx, single_cols = _compact_axis(cand_q)
    return rows, row_idx, cols, col_idx, single_rows and single_cols


@njit(cache=True)
def placed_centres(pose, own):
    """The centres (K, 2) of the boxes own (K, 3) (the agent's frame) in the ego frame
    under its pose (3,) (x m, y m, yaw rad): ``R(yaw) t + (x, y)``, each coordinate as
    ``t_x * cos + t_y * (-sin)`` (y: ``t_x * sin + t_y * cos``) plus the offset. (numpy's
    ``own[:, :2] @ R^T`` goes through BLAS, whose kernels may fuse the multiply-adds:
    the same values to the last bit or two.)"""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    centres = np.empty((own.shape[0], 2))
    for k in range(own.shape[0]):
        centres[k, 0] = own[k, 0] * c + own[k, 1] * -s + pose[0]
        centres[k, 1] = own[k, 0] * s + own[k, 1] * c + pose[1]
    return centres


@njit(cache=True)
def scored_pairs(land_xy, centres, tau2, lam, use_edge, land_features, box_features, radius2,
                 tau1, cached):
    """One matching of ``matching.StarGraphMatcher``: the gated candidate pairs
    (:func:`gated_pairs`) scored S = lam * S_dis (lam = 0: no distance term) + S_edge
    (with ``use_edge``, :func:`edge_similarity`; reused from ``cached`` = (cand_p, cand_q,
    leaves, partner, S_edge) of an earlier call when the pairs and the initial matches
    are the same), and the assignment's shortcut: when every landmark and every box has a
    single candidate and every score is > 0, the pairs with S >= tau1 are the assignment.

    Returns (assigned?, landmark (P,), box (P,), S (P,) of the assignment when the
    shortcut applies (else empty), then the candidates (cand_p, cand_q, S) for the full
    assignment, and the new cache (cand_p, cand_q, leaves, partner, S_edge)).
    """
    cand_p, cand_q, dis, leaves, partner = gated_pairs(land_xy, centres, tau2)
    score = np.empty(cand_p.size)
    for k in range(cand_p.size):
        score[k] = lam * math.exp(-dis[k])
    edge = cached[4]
    if use_edge:
        old_p, old_q, old_leaves, old_partner = cached[0], cached[1], cached[2], cached[3]
        same = old_p.size == cand_p.size and old_leaves.size == leaves.size
        for k in range(cand_p.size if same else 0):
            same = same and old_p[k] == cand_p[k] and old_q[k] == cand_q[k]
        for k in range(leaves.size if same else 0):
            same = same and old_leaves[k] == leaves[k] and old_partner[k] == partner[k]
        if not same:
            edge = edge_similarity(land_features, box_features, cand_p, cand_q, leaves, partner,
                                   radius2)
        for k in range(cand_p.size):
            score[k] = score[k] + edge[k]
    single = compact_pairs(cand_p, cand_q)[4]
    for k in range(cand_p.size):
        single = single and score[k] > 0
    kept = np.zeros(cand_p.size, dtype=np.bool_)
    if single:
        for k in range(cand_p.size):
            kept[k] = score[k] >= tau1
    return (single, cand_p[kept], cand_q[kept], score[kept], cand_p, cand_q, score,
            (cand_p, cand_q, leaves, partner, edge))


@njit(cache=True)
def _matches(pose, own_poses, land_xy, tau2, lam, use_edge, land_features, box_features,
             radius2, tau1, cache):
    """One ``StarGraphMatcher.match`` under ``pose`` (3,) with gate ``tau2`` (m) when the
    assignment's shortcut applies: (shortcut applied?, landmark (P,), box (P,), new cache);
    no landmarks or no boxes: no matches, the cache kept."""
    if land_xy.shape[0] == 0 or own_poses.shape[0] == 0:
        return True, cache[0][:0].copy(), cache[0][:0].copy(), cache
    single, land, box, _, _, _, _, cache = scored_pairs(
        land_xy, placed_centres(pose, own_poses), tau2, lam, use_edge, land_features,
        box_features, radius2, tau1, cache,
    )
    return single, land, box, cache


@njit(cache=True)
def attempt_rounds(start, own_poses, own_info, own_cov, land_poses, land_features, land_cov,
                   box_features, prior_z, prior_info, tau2, coarse_tau2, lam, use_edge, radius2,
                   tau1, min_matches, rounds, kernel, delta, max_iterations, tolerance, min_diag,
                   inlier_chi2, fit_tolerance, difference):
    """RoCo's match-optimise rounds for one collaborator (``roco._attempt`` with per-round
    single-vertex solves).

    start (3,): first pose estimate T_{j->i}; own_poses (K, 3) / own_info (K, 3, 3) /
    own_cov (K, 3, 3): its boxes (its frame), their information and covariance;
    land_poses (L, 3) / land_cov (L, 3, 3): the map's landmarks (ego frame) and their
    covariance; land_features (5, L) / box_features (5, K): the pose features; prior_z
    (3,) / prior_info (3, 3): the prior edge (reported pose). Matching settings as
    ``StarGraphMatcher`` (tau2, coarse_tau2 m, coarse_tau2 <= 0: no coarse gate; lam = 0:
    no distance term); at most ``rounds`` rounds; solver settings as
    :func:`solve_pose_edges`. difference: each round's edges carry the information of box
    minus landmark, ``(own_cov + land_cov)^-1`` (the landmark held fixed has the error of
    the box that created it); else the box's own_info alone.

    When the rounds end solved with at least ``min_matches`` edges of chi2 <=
    ``inlier_chi2`` and ``fit_tolerance`` > 0, also the significance test's statistic
    (``roco._correction_statistic``: :func:`wald_statistic`
    with the covariance of box minus landmark, LM stop ``fit_tolerance``); else nan.

    Returns (done, pose (3,), landmark ids (P,), box ids (P,), solved, chi2 (P,),
    landmarks (P, 3), rounds run, solver iterations, statistic); done = False when a
    round's matching needs the full assignment (the rest is then meaningless).
    """
    empty = np.zeros(0, dtype=np.int64)
    cache = (empty, empty.copy(), empty.copy(), empty.copy(), np.zeros(0))
    land_xy = np.ascontiguousarray(land_poses[:, :2])
    pose = start.copy()
    match_land, match_box = empty.copy(), empty.copy()
    chi2, landmarks = np.zeros(0), np.zeros((0, 3))
    solved, outer, solver = False, 0, 0
    for _ in range(rounds):
        single, land, box, cache = _matches(pose, own_poses, land_xy, tau2, lam, use_edge,
                                            land_features, box_features, radius2, tau1, cache)
        if single and outer == 0 and land.size < min_matches and coarse_tau2 > 0:
            single, land, box, cache = _matches(pose, own_poses, land_xy, coarse_tau2, lam,
                                                use_edge, land_features, box_features, radius2,
                                                tau1, cache)
        if not single:
            return (False, pose, match_land, match_box, solved, chi2, landmarks, outer, solver,
                    np.nan)
        if outer and _same(land, match_land) and _same(box, match_box):
            break
        outer += 1
        match_land, match_box = land, box
        solved = land.size >= min_matches
        if not solved:
            break
        landmarks = land_poses[match_land]
        if difference:
            edge_info = inverse_covariances(own_cov[match_box] + land_cov[match_land])
        else:
            edge_info = own_info[match_box]
        pose, chi2, _, _, iterations, _ = solve_pose_edges(
            pose, landmarks, own_poses[match_box], edge_info, prior_z, prior_info,
            kernel, delta, max_iterations, tolerance, min_diag,
        )
        solver += iterations
    statistic = np.nan
    if solved and fit_tolerance > 0 and np.count_nonzero(chi2 <= inlier_chi2) >= min_matches:
        statistic = wald_statistic(
            pose, landmarks, own_poses[match_box], own_cov[match_box] + land_cov[match_land],
            prior_z, kernel, delta, max_iterations, fit_tolerance, min_diag,
        )
    return True, pose, match_land, match_box, solved, chi2, landmarks, outer, solver, statistic


@njit(cache=True)
def _same(a, b):
    """``np.array_equal`` of two 1-d integer arrays."""
    if a.size != b.size:
        return False
    for k in range(a.size):
        if a[k] != b[k]:
            return False
    return True
