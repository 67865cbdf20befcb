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
(:func:`edge_similarity`: every candidate pair scored against every matched leaf; with
the star graphs' neighbour radius most (pair, leaf) combinations are not leaves of both
stars, so one loop skips them), the assignment (:func:`scored_pairs`: its shortcut, or
the Kuhn-Munkres solver of :func:`max_weight_assignment`;
tests/test_matching_kernels.py), a collaborator's whole match-optimise loop
(:func:`attempt_rounds`; tests/test_roco_kernels.py compares it with a Python loop of the
same steps) and the map after an accepted collaborator (:func:`committed_map`). They share
this module with the solver because a compiled function calls only functions of its own
module, and uses only records defined in it (numba's on-disk cache notices edits to a
function's own file only).

The kernels take their inputs as small records defined here once (``typing.NamedTuple``,
which numba compiles as tuples with named fields): the solver's settings
(:class:`Solver`), a prior edge (:class:`PriorEdge`), the edges of a single-vertex problem
(:class:`PoseEdges`) or of a pose graph (:class:`GraphEdges`), the matcher's settings
(:class:`MatchSettings`), a collaborator's boxes (:class:`AgentBoxes`), RoCo's map
(:class:`LandmarkMap`, :class:`Observations`), the rounds' settings
(:class:`RoundSettings`) and state (:class:`RoundState`). From Python a record is passed
as a plain tuple, ``tuple(record)``: numba types a named tuple argument field by field in
Python on every call, a plain one in C (several times faster, docs/performance.md); the
kernels name it again on entry (``Record(*argument)``, free once compiled), so either form
is accepted. The other way, a named tuple is boxed by calling its class, so the rounds and
the commit, called per collaborator, return their records' fields as plain tuple literals
(in the record's field order) for the caller to name.

Kernel codes: 0 = least squares, 1 = Huber, 2 = Cauchy (as
:func:`~roco_env.policies.posegraph.robust_kernel`, delta in whitened units).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

__all__ = ["KERNEL_CODES", "AgentBoxes", "GatedPairs", "GraphEdges", "LandmarkMap",
           "Linearisation", "MatchSettings", "Observations", "PoseEdges", "PriorEdge",
           "PriorTerms", "RefineSettings", "RoundSettings", "RoundState", "Solver",
           "attempt_rounds", "committed_map", "compact_pairs", "damped_step",
           "edge_similarity", "edge_similarity_sums", "empty_match_cache", "evaluate_edges",
           "gated_pairs", "inverse_covariances", "max_weight_assignment", "normal_sums",
           "pair_information", "placed_centres", "placed_landmarks", "pose_edges",
           "prior_terms", "refine_pose", "refine_starts", "rotate_information", "scored_pairs",
           "solve_graph", "solve_pose", "solve_pose_edges", "wald_statistic"]

KERNEL_CODES = {None: 0, "huber": 1, "cauchy": 2}


class Solver(NamedTuple):
    """Levenberg-Marquardt settings: the robust kernel's code (:data:`KERNEL_CODES`) and
    delta (whitened units), the cap on linearisations, the stop on an accepted step's
    relative cost decrease or largest component, and the smallest damping diagonal."""

    kernel: int
    delta: float
    max_iterations: int
    tolerance: float
    min_diag: float


class PriorEdge(NamedTuple):
    """A prior edge from the fixed identity vertex (the ego) to the agent: measurement
    z (3,) (x m, y m, yaw rad) and information (3, 3) (zeros: no prior)."""

    z: np.ndarray
    information: np.ndarray


class PriorTerms(NamedTuple):
    """The constant terms of a :class:`PriorEdge` (:func:`prior_terms`): its Jacobian
    J_p = blockdiag(R_z^T, 1) (3, 3), offset J_p z (3,), information Omega_p (3, 3),
    hessian J_p^T Omega_p J_p (3, 3) and weighted Jacobian Omega_p J_p (3, 3); the
    residual is J_p pose - offset, yaw wrapped."""

    jacobian: np.ndarray
    offset: np.ndarray
    information: np.ndarray
    hessian: np.ndarray
    weighted: np.ndarray


class PoseEdges(NamedTuple):
    """E observation edges of one agent vertex to fixed landmarks (:func:`pose_edges`):
    landmark centres land_xy (E, 2), measured translations t_z (E, 2), landmark yaw minus
    measured yaw ``angle`` (E,) and the information ``info`` (E, 3, 3) in the rotated
    residual frame (:func:`rotate_information`)."""

    land_xy: np.ndarray
    t_z: np.ndarray
    angle: np.ndarray
    info: np.ndarray


class Linearisation(NamedTuple):
    """Per-edge terms of :class:`PoseEdges` at a pose (:func:`evaluate_edges`): chi2 (E,),
    u (E, 2) = R(-yaw)(t_l - t), info_e (E, 3) = Omega e, IRLS weight (E,)."""

    chi2: np.ndarray
    u: np.ndarray
    info_e: np.ndarray
    weight: np.ndarray


class GraphEdges(NamedTuple):
    """The edges of a pose graph (:func:`solve_graph`): vertices 0 .. n_agents - 1 are
    agents, the rest landmarks; the first n_obs edges observe landmark ``to_v`` (a
    landmark index) from agent ``from_v``, the others are priors agent -> agent;
    measurement yaw meas_yaw (E,), R_z^T t_z meas_offset (E, 2), information (E, 3, 3)."""

    n_agents: int
    n_obs: int
    from_v: np.ndarray
    to_v: np.ndarray
    meas_yaw: np.ndarray
    meas_offset: np.ndarray
    info: np.ndarray


class NormalEquations(NamedTuple):
    """Blocks of a pose graph's normal equations: H_aa (3N, 3N), H_al (3N, 3M), the
    block-diagonal H_ll (M, 3, 3), g_a (3N,), g_l (M, 3)."""

    h_aa: np.ndarray
    h_al: np.ndarray
    h_ll: np.ndarray
    g_a: np.ndarray
    g_l: np.ndarray


class GatedPairs(NamedTuple):
    """The gate's pairs of a matching (:func:`gated_pairs`): candidate pairs of landmark
    p (C,) and box q (C,) with their centre distance (C,, m), and the initial matches:
    the landmarks with a box within the gate (leaves (H,)) and their nearest box
    (partner (H,))."""

    p: np.ndarray
    q: np.ndarray
    distance: np.ndarray
    leaves: np.ndarray
    partner: np.ndarray


class RefineSettings(NamedTuple):
    """A refinement's settings (:func:`refine_pose`): matching gate (m), the fewest
    matched boxes a round needs, the solver's settings (:class:`Solver`, or its plain
    tuple)."""

    gate: float
    min_matches: int
    solver: Solver


class MatchSettings(NamedTuple):
    """The star-graph matching's settings (:func:`scored_pairs`): weight ``lam`` of
    S_dis (0: not used), whether S_edge is used, the squared star-graph radius radius2
    (m^2; < 0: no radius) and the bar tau1 on S."""

    lam: float
    use_edge: bool
    radius2: float
    tau1: float


class AgentBoxes(NamedTuple):
    """One collaborator's boxes as RoCo's rounds use them: poses (K, 3) in its own frame,
    information (K, 3, 3) and covariance (K, 3, 3) in the box frame, pose features (5, K)
    (``matching.pose_features``), and its reported pose (3,) (the prior edge's
    measurement)."""

    poses: np.ndarray
    information: np.ndarray
    covariance: np.ndarray
    features: np.ndarray
    reported: np.ndarray


class LandmarkMap(NamedTuple):
    """RoCo's landmarks: poses (L, 3) in the ego frame, pose features (5, L)
    (``matching.pose_features``) and the covariance (L, 3, 3) of the box that created
    each."""

    poses: np.ndarray
    features: np.ndarray
    covariance: np.ndarray


class Observations(NamedTuple):
    """RoCo's observations (O,): observation o is box ``box[o]`` of agent ``agent[o]``
    (0 = the ego) seeing landmark ``land[o]``."""

    agent: np.ndarray
    box: np.ndarray
    land: np.ndarray


class RoundSettings(NamedTuple):
    """RoCo's match-optimise rounds (:func:`attempt_rounds`; the matcher's and the
    solver's settings come beside them): the matching gate tau2 (m), the first round's
    wider gate coarse_tau2 (m; <= 0: none), min_matches, the round cap, the prior edges'
    information (3, 3), inlier_chi2, the significance fit's LM stop (0: no significance
    test), whether an edge carries the information of box minus landmark (``difference``;
    else the box's own), and whether the rounds pause for a joint solve of the whole graph
    (``joint``)."""

    tau2: float
    coarse_tau2: float
    min_matches: int
    rounds: int
    prior_information: np.ndarray
    inlier_chi2: float
    fit_tolerance: float
    difference: bool
    joint: bool


class RoundState(NamedTuple):
    """Where a collaborator's rounds stand: its pose estimate (3,), matched landmark ids
    and box indices (P,), whether the last matching had min_matches, the matched edges'
    chi2 (P,) and landmarks (P, 3) at the estimate, the rounds run and the solver's
    iterations so far."""

    pose: np.ndarray
    match_land: np.ndarray
    match_box: np.ndarray
    solved: bool
    chi2: np.ndarray
    landmarks: np.ndarray
    outer: int
    iterations: int


@njit(cache=True)
def evaluate_edges(pose, edges, kernel, delta):
    """Residuals of the :class:`PoseEdges` at the pose (3,) (x m, y m, yaw rad) with the
    robust kernel (code, delta). Returns (sum of rho, :class:`Linearisation`)."""
    edges = PoseEdges(*edges)
    land_xy, t_z, angle, info = edges.land_xy, edges.t_z, edges.angle, edges.info
    x, y, yaw = pose[0], pose[1], pose[2]
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
    return total, Linearisation(chi2, u, info_e, weight)


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
def normal_sums(yaw, info, point, weight, with_gradient):
    """Gauss-Newton Hessian (3, 3) and gradient (3,) of the edges with information info
    (E, 3, 3) (rotated residual frame) linearised at ``point`` (:class:`Linearisation`
    at the pose's yaw, rad), each weighted by weight (E,) (the gradient is zeros unless
    ``with_gradient``), in the (x, y, yaw) coordinates of the pose.

    With m = (-u_y, u_x): inner = sum w N^T Omega N (N = I + m e3^T), H = Q inner Q^T,
    g = -Q sum w N^T Omega e, Q = blockdiag(R(yaw), 1).
    """
    c, s = math.cos(yaw), math.sin(yaw)
    point = Linearisation(*point)
    u, info_e = point.u, point.info_e
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
    """Wrap to [-pi, pi) as ``posegraph._wrap`` (float ``%``: fmod with numpy's sign fix-up)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


@njit(cache=True)
def _pose_cost(pose, edges, prior, solver):
    """Robust cost and linearisation point at ``pose`` (3,): :func:`evaluate_edges` plus
    the quadratic prior edge (:class:`PriorTerms`; a zero-information prior,
    :func:`_no_prior`, adds exact zeros). Returns (cost, :class:`Linearisation`, prior
    residual (3,))."""
    cost, point = evaluate_edges(pose, edges, solver.kernel, solver.delta)
    e_p = np.empty(3)
    j_p, offset, info_p = prior.jacobian, prior.offset, prior.information
    for r in range(3):
        e_p[r] = j_p[r, 0] * pose[0] + j_p[r, 1] * pose[1] + j_p[r, 2] * pose[2] - offset[r]
    e_p[2] = _wrap(e_p[2])
    quad = 0.0
    for b in range(3):
        quad += (e_p[0] * info_p[0, b] + e_p[1] * info_p[1, b] + e_p[2] * info_p[2, b]) * e_p[b]
    return cost + quad, point, e_p


@njit(cache=True)
def solve_pose(initial, edges, prior, solver):
    """Levenberg-Marquardt of one agent vertex against fixed landmarks: the loop of
    :func:`solve_graph` with the single vertex's linearisation (same stopping rules, same
    arithmetic per edge).

    initial (3,) pose; edges: :class:`PoseEdges`; prior: the prior edge's
    :class:`PriorTerms` (:func:`_no_prior` for none: its zeros change nothing); solver:
    :class:`Solver`. Returns (pose (3,), chi2 (E,) at it, initial cost, cost, iterations,
    converged).
    """
    x = initial.copy()
    cost, point, e_p = _pose_cost(x, edges, prior, solver)
    weighted = prior.weighted
    initial_cost, lam, iterations, converged = cost, 1e-4, 0, False
    while iterations < solver.max_iterations and not converged:
        iterations += 1
        hess, grad = normal_sums(x[2], edges.info, point, point.weight, True)
        hess += prior.hessian
        for r in range(3):
            grad[r] += weighted[0, r] * e_p[0] + weighted[1, r] * e_p[1] + weighted[2, r] * e_p[2]
        while True:
            step_delta, step = damped_step(hess, grad, lam, solver.min_diag)
            trial = x + step_delta
            trial[2] = _wrap(trial[2])
            t_cost, t_point, t_e_p = _pose_cost(trial, edges, prior, solver)
            if t_cost <= cost:
                break
            lam *= 10.0
            if lam > 1e12:
                converged = True  # no damping reduces the cost: a (local) minimum
                break
        if converged:
            break
        decrease = cost - t_cost
        x, cost, point, e_p = trial, t_cost, t_point, t_e_p
        lam = max(lam / 10.0, 1e-12)
        converged = decrease <= solver.tolerance * max(cost, 1e-300) or step <= solver.tolerance
    return x, point.chi2, initial_cost, cost, iterations, converged


@njit(cache=True)
def _graph_cost(x, edges, kernel, delta):
    """Robust cost of the pose graph's :class:`GraphEdges` at the vertices x (V, 3)
    (agents, then landmarks) with the robust kernel (code, delta), and per edge: e (E, 3),
    chi2 (E,), IRLS weight (E,; 1 on prior edges), and the Jacobian terms c, s, w_x, w_y
    (E,) of ``Z^{-1} T_a^{-1} T_b`` (``posegraph._residuals``)."""
    n_agents, n_obs, from_v, to_v = edges.n_agents, edges.n_obs, edges.from_v, edges.to_v
    meas_yaw, meas_offset, info = edges.meas_yaw, edges.meas_offset, edges.info
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
def _graph_normal_equations(edges, n_land, e, weight, terms):
    """:class:`NormalEquations` of the weighted :class:`GraphEdges` with M = n_land
    landmarks, from their residuals e (E, 3), weights (E,) and Jacobian terms (E, 4)
    (:func:`_graph_cost`): each edge adds J^T w Omega J and J^T w Omega e, J = [J_a | J_b]
    (3, 6) its Jacobian; rows/columns 3-5 belong to the landmark (observation edges) or
    to the second agent (prior edges)."""
    n_agents, n_obs, from_v, to_v, info = (edges.n_agents, edges.n_obs, edges.from_v,
                                           edges.to_v, edges.info)
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
    return NormalEquations(h_aa, h_al, h_ll, g_a, g_l)


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
def _graph_step(normal, rows, row_start, free, lam, min_diag):
    """LM step (d_agents (3N,), d_landmarks (M, 3), max |component|) of the
    :class:`NormalEquations` with Marquardt damping ``lam``; the landmarks are eliminated
    by the Schur complement and the agents not in ``free`` (coordinate indices) stay fixed.
    H_al's block column of landmark m is zero outside the coordinate rows
    ``rows[row_start[m]:row_start[m + 1]]`` (those of the agents observing it), so only
    those rows are visited."""
    h_aa, h_al, h_ll, g_a, g_l = normal.h_aa, normal.h_al, normal.h_ll, normal.g_a, normal.g_l
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
def _landmark_rows(edges, n_land):
    """Per landmark (n_land of them), the coordinate rows (3 per agent, agents in
    increasing order) of the agents observing it in the :class:`GraphEdges`, as CSR
    (rows, start (M + 1,))."""
    n_agents, n_obs, from_v, to_v = edges.n_agents, edges.n_obs, edges.from_v, edges.to_v
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
def solve_graph(x0, edges, free, solver):
    """Levenberg-Marquardt on a pose graph (``posegraph.optimize``): vertices x0 (V, 3),
    agents first then landmarks, joined by the :class:`GraphEdges`; ``free``: coordinate
    indices of the agents that move; solver: :class:`Solver`. Starts with lam = 1e-4; an
    accepted step (cost not raised) divides lam by 10, a rejected one multiplies it by 10
    until 1e12 (no progress: converged); stops after ``max_iterations`` linearisations, or
    when an accepted step's relative cost decrease or largest component is below
    ``tolerance``. Returns (x (V, 3), chi2 (E,), initial cost, cost, iterations,
    converged)."""
    edges, solver = GraphEdges(*edges), Solver(*solver)
    n_agents, kernel, delta = edges.n_agents, solver.kernel, solver.delta
    n_land = x0.shape[0] - n_agents
    rows, row_start = _landmark_rows(edges, n_land)
    x = x0.copy()
    cost, e, chi2, weight, terms = _graph_cost(x, edges, kernel, delta)
    initial_cost, lam, iterations, converged = cost, 1e-4, 0, False
    while iterations < solver.max_iterations and not converged:
        iterations += 1
        normal = _graph_normal_equations(edges, n_land, e, weight, terms)
        while True:
            d_a, d_l, step = _graph_step(normal, rows, row_start, free, lam, solver.min_diag)
            trial = x.copy()
            for v in range(x.shape[0]):
                for i in range(3):
                    trial[v, i] += d_a[3 * v + i] if v < n_agents else d_l[v - n_agents, i]
                trial[v, 2] = _wrap(trial[v, 2])
            t_cost, t_e, t_chi2, t_weight, t_terms = _graph_cost(trial, edges, kernel, delta)
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
        converged = decrease <= solver.tolerance * max(cost, 1e-300) or step <= solver.tolerance
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
def pose_edges(landmarks, measurement, information):
    """:class:`PoseEdges` of E edges as given: fixed landmarks (E, 3), measurements
    (E, 3) (the landmarks in the agent's frame) and information (E, 3, 3) (box frame)."""
    return PoseEdges(np.ascontiguousarray(landmarks[:, :2]),
                     np.ascontiguousarray(measurement[:, :2]),
                     landmarks[:, 2] - measurement[:, 2],
                     rotate_information(np.ascontiguousarray(information),
                                        np.ascontiguousarray(measurement[:, 2])))


@njit(cache=True)
def wald_statistic(start, landmarks, own, covariance, reported, solver):
    """Robust Wald statistic of a correction (RoCo's significance test).

    The agent pose is fitted from ``start`` (3,) to its P edges alone (no prior): fixed
    landmarks (P, 3), its boxes ``own`` (P, 3) in its frame, each edge with the
    information ``covariance^-1`` (covariance (P, 3, 3) in the box frame), the robust
    kernel and the LM rules of :func:`solve_pose` (solver: :class:`Solver`); then
    ``d = fit - reported`` (yaw wrapped) is weighed by the sandwich ``A^-1 B A^-1``,
    A = sum w J^T Omega J, B = sum w^2 J^T Omega J with w the IRLS weights at the fit:
    returns ``d^T A B^-1 A d``.
    """
    solver = Solver(*solver)
    edges = pose_edges(landmarks, own, inverse_covariances(covariance))
    pose = solve_pose(start, edges, _no_prior(), solver)[0]
    point = evaluate_edges(pose, edges, solver.kernel, solver.delta)[1]
    weight = point.weight
    bread = normal_sums(pose[2], edges.info, point, weight, False)[0]
    meat = normal_sums(pose[2], edges.info, point, weight * weight, False)[0]
    d = pose - reported
    d[2] = _wrap(d[2])
    ad = bread @ d
    solved = damped_step(meat, -ad, 0.0, solver.min_diag)[0]  # B^-1 A d
    return ad[0] * solved[0] + ad[1] * solved[1] + ad[2] * solved[2]


@njit(cache=True)
def refine_pose(initial, land_poses, own_poses, own_info, settings):
    """Up to two rounds of nearest-centre matching and a robust single-vertex solve (the
    refinement of roco_antialias's hypotheses, :func:`refine_starts`).

    Each round maps the agent's boxes own_poses (K, 3) (its frame) into the landmarks'
    frame with the current pose (initial (3,) first), pairs every box with its nearest
    landmark (land_poses (L, 3); lowest index among equal distances) closer than the
    gate, and solves the pose from those pairs (boxes' information own_info (K, 3, 3),
    no prior; LM rules of :func:`solve_pose`); settings: :class:`RefineSettings`. The
    second round runs only when the pairs changed. Returns (pose (3,), True), or
    (initial, False) when fewer than ``min_matches`` boxes match in a round.
    """
    by_x = np.argsort(land_poses[:, 0])
    return _refine_sorted(initial, (land_poses, by_x, land_poses[by_x, 0]), own_poses, own_info,
                          _refine_settings(settings))


@njit(cache=True)
def _refine_settings(settings):
    """The :class:`RefineSettings` (or its plain tuple, with the solver's as a plain tuple)
    named again, its :class:`Solver` too."""
    settings = RefineSettings(*settings)
    return RefineSettings(settings.gate, settings.min_matches, Solver(*settings.solver))


@njit(cache=True)
def _refine_sorted(initial, sorted_land, own_poses, own_info, settings):
    """:func:`refine_pose` with the landmarks given as (poses (L, 3), their order by x
    (L,), their sorted x (L,)): only landmarks within the gate in x (with a margin far
    above rounding) can be nearer than the gate; ties go to the lowest index, as in a
    scan."""
    land_poses, by_x, sorted_x = sorted_land
    gate, min_matches = settings.gate, settings.min_matches
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
        edges = pose_edges(land_poses[nearest[box]], own_poses[box], own_info[box])
        pose = solve_pose(pose, edges, _no_prior(), settings.solver)[0]
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
def pair_information(landmarks, own, pose, gate, slack_t, slack_r):
    """Information (3, 3) of the agent's pose (3,) (x m, y m, yaw rad) from the pairs of each
    of its boxes (``own`` = (poses (K, 3) in its frame, mapped by ``pose``, var_t (K,),
    var_r (K,))) with the nearest landmark (``landmarks``, the same three arrays, L rows)
    closer than ``gate`` m, as the refinement pairs them, and the number of pairs (the
    ambiguity diagnosis, ``roco_env.policies.ambiguity``, step 1).

    A pair's position residual has variance ``land_var_t + own_var_t + slack_t`` (m^2) in x
    and y, its heading residual ``land_var_r + own_var_r + slack_r`` (rad^2); the mapped
    centre's derivative in yaw is its offset from the agent's origin turned by 90 degrees."""
    land_poses, land_var_t, land_var_r = landmarks
    own_poses, own_var_t, own_var_r = own
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
def refine_starts(peaks, seeds, land_poses, own_poses, own_info, settings):
    """The refined hypotheses (R, 3) of one collaborator (``roco_env.policies.antialias``,
    step 1): the vote peaks (H, 3), then each seed (S, 3) (the reported pose, a track's
    prediction) unless within 0.5 m / 0.5 deg of a peak (it would refine to the same
    pose), refined in turn by :func:`refine_pose` (arguments as there, ``settings`` its
    :class:`RefineSettings`); a start matching too few boxes, or refining to within
    0.3 m / 0.3 deg of an earlier result, adds none."""
    settings = _refine_settings(settings)
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
    sorted_land = (land_poses, by_x, land_poses[by_x, 0])
    refined = np.empty((n_starts, 3))
    count = 0
    for k in range(n_starts):
        pose, ok = _refine_sorted(starts[k], sorted_land, own_poses, own_info, settings)
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
def prior_terms(prior):
    """The :class:`PriorTerms` of the :class:`PriorEdge` identity -> agent measuring z
    (3,) with information Omega_p (3, 3), with the edge's constant Jacobian
    J_p = blockdiag(R_z^T, 1); its residual is J_p pose - J_p z, yaw wrapped."""
    prior = PriorEdge(*prior)
    z, info_p = prior.z, prior.information
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
    return PriorTerms(j_p, offset, info_p.copy(), hess, ip_jp)


@njit(cache=True)
def _no_prior():
    """:func:`prior_terms` of a prior edge with zero information (no prior)."""
    return prior_terms(PriorEdge(np.zeros(3), np.zeros((3, 3))))


@njit(cache=True)
def solve_pose_edges(initial, landmarks, measurement, information, prior, solver):
    """:func:`solve_pose` from the edges as given (:func:`pose_edges`: landmarks (E, 3),
    measurements (E, 3), information (E, 3, 3)) and the :class:`PriorEdge` (zero
    information: no prior), whose terms (:func:`prior_terms`) are built here."""
    return solve_pose(initial, pose_edges(landmarks, measurement, information),
                      prior_terms(prior), Solver(*solver))


@njit(cache=True)
def edge_similarity_sums(cand, leaf, pairs, centres, radius2):
    """S_edge (C,) of the :class:`GatedPairs`: mean over usable leaves h of
    exp(-sqrt(max(cand[c] . leaf[:, h], 0))).

    cand (C, 11) / leaf (11, H): the bilinear factors of ||T_pm T_qn^{-1} - I||_F^2;
    a leaf is usable for candidate c when it is neither p nor q's partner, and (radius2
    >= 0) both centre offsets are within the radius: centres (C, 4) = (p_x, p_y, q_x,
    q_y) and leaf rows 11-14 of ``leaf`` hold (m_x, m_y, n_x, n_y). 0 without a usable leaf.
    """
    cand_p, cand_q, leaves, partner = pairs.p, pairs.q, pairs.leaves, pairs.partner
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
def edge_similarity(land, box, pairs, radius2):
    """S_edge (C,) of the candidate pairs of the :class:`GatedPairs` (landmark p, box q)
    given their initial matches (landmarks m = leaves, boxes n = partner = A(m)), from the
    pose features (5, L) / (5, K) (x, y, x^2 + y^2, cos yaw, sin yaw) of the landmarks and
    the boxes (``matching.pose_features``): the (C, 11) candidate and (11, H) leaf factors
    of ||T_pm T_qn^{-1} - I||_F^2 (``matching`` module docstring), summed by
    :func:`edge_similarity_sums`; radius2 < 0: no neighbour radius."""
    pairs = GatedPairs(*pairs)
    cand_p, cand_q, leaves, partner = pairs.p, pairs.q, pairs.leaves, pairs.partner
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
    return edge_similarity_sums(cand, leaf, pairs, centres, radius2)


@njit(cache=True)
def gated_pairs(land_xy, centres, tau2):
    """Candidate pairs of the gate and the initial matches, without (L x K) temporaries.

    land_xy (L, 2), centres (K, 2) in the ego frame; distance = sqrt(dx^2 + dy^2).
    Returns (p (C,), q (C,), distance (C,)) of the pairs with distance <= tau2 in row-major
    (p, then q) order, and (leaves (H,), partner (H,)): every landmark whose nearest box
    (lowest index among equal distances) is within the gate, with that box, as
    :class:`GatedPairs`. A pair whose |dx| or |dy| alone exceeds the gate (by more than
    rounding) is skipped unmeasured; the boxes are sorted by x once, so each landmark scans
    only its window in x.
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
    return GatedPairs(cand_p[:k].copy(), cand_q[:k].copy(), dis[:k].copy(), leaves[:h],
                      partner[:h])


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
def max_weight_assignment(weights):
    """Maximum-weight one-to-one assignment of the rows and columns of ``weights`` (R, Q):
    (rows (min(R, Q),) increasing, their columns), as
    ``scipy.optimize.linear_sum_assignment(weights, maximize=True)`` gives it, ties
    included: its shortest augmenting path algorithm (Crouse 2016) on the negated weights,
    transposed when there are fewer columns than rows, step for step."""
    transpose = weights.shape[1] < weights.shape[0]
    n_rows, n_cols = min(weights.shape), max(weights.shape)
    cost = np.empty((n_rows, n_cols))  # negated (and transposed) by loops: compiles faster
    for i in range(n_rows):
        for j in range(n_cols):
            cost[i, j] = -weights[j, i] if transpose else -weights[i, j]
    u, v = np.zeros(n_rows), np.zeros(n_cols)
    shortest = np.empty(n_cols)
    path = np.empty(n_cols, dtype=np.int64)
    col4row = np.empty(n_rows, dtype=np.int64)
    row4col = np.empty(n_cols, dtype=np.int64)
    for j in range(n_cols):
        path[j] = row4col[j] = -1
    for i in range(n_rows):
        col4row[i] = -1
    seen_rows = np.empty(n_rows, dtype=np.bool_)
    seen_cols = np.empty(n_cols, dtype=np.bool_)
    remaining = np.empty(n_cols, dtype=np.int64)
    for current in range(n_rows):
        # The shortest augmenting path from row ``current`` to a free column (the sink).
        min_val = 0.0
        n_remaining = n_cols
        for it in range(n_cols):
            remaining[it] = n_cols - it - 1  # reversed: a constant matrix gives the identity
            seen_cols[it] = False
            shortest[it] = math.inf
        for i in range(n_rows):
            seen_rows[i] = False
        sink, i = -1, current
        while sink == -1:
            index, lowest = -1, math.inf
            seen_rows[i] = True
            for it in range(n_remaining):
                j = remaining[it]
                r = min_val + cost[i, j] - u[i] - v[j]
                if r < shortest[j]:
                    path[j] = i
                    shortest[j] = r
                # Among equally short ones, a free column (a new sink) wins.
                if shortest[j] < lowest or (shortest[j] == lowest and row4col[j] == -1):
                    lowest = shortest[j]
                    index = it
            min_val = lowest
            if min_val == math.inf:
                raise ValueError("infeasible assignment")
            j = remaining[index]
            if row4col[j] == -1:
                sink = j
            else:
                i = row4col[j]
            seen_cols[j] = True
            n_remaining -= 1
            remaining[index] = remaining[n_remaining]
        # Update the duals, then augment along the path.
        u[current] += min_val
        for i in range(n_rows):
            if seen_rows[i] and i != current:
                u[i] += min_val - shortest[col4row[i]]
        for j in range(n_cols):
            if seen_cols[j]:
                v[j] -= min_val - shortest[j]
        j = sink
        while True:
            i = path[j]
            row4col[j] = i
            col4row[i], j = j, col4row[i]
            if i == current:
                break
    if not transpose:
        return np.arange(n_rows), col4row
    # Transposed: col4row maps each column of weights to its row; listed by row.
    by_row = np.empty(n_cols, dtype=np.int64)
    for row in range(n_cols):
        by_row[row] = -1
    for col in range(n_rows):
        by_row[col4row[col]] = col
    rows, cols = np.empty(n_rows, dtype=np.int64), np.empty(n_rows, dtype=np.int64)
    count = 0
    for row in range(n_cols):
        if by_row[row] >= 0:
            rows[count], cols[count] = row, by_row[row]
            count += 1
    return rows, cols


@njit(cache=True)
def scored_pairs(land_xy, centres, tau2, land_features, box_features, settings, cached):
    """One star-graph matching (``matching``'s module docstring): the gated candidate pairs
    (:func:`gated_pairs`, gate tau2 m) scored S = lam * S_dis + S_edge (settings:
    :class:`MatchSettings`; with ``use_edge``, :func:`edge_similarity` from the pose
    features (5, L) / (5, K), reused from ``cached`` = (:class:`GatedPairs`, S_edge) of an
    earlier call when the pairs and the initial matches are the same), then the
    maximum-weight one-to-one assignment, whose pairs with S >= tau1 are the matches. When
    every landmark and every box has a single candidate and every score is > 0, the
    assignment takes every pair (the usual sparse scene); else
    :func:`max_weight_assignment` over the candidates (0 elsewhere).

    Returns (landmark (P,), box (P,), S (P,)), sorted by landmark, and the new cache.
    """
    settings = MatchSettings(*settings)
    pairs = gated_pairs(land_xy, centres, tau2)
    cand_p, cand_q = pairs.p, pairs.q
    score = np.empty(cand_p.size)
    for k in range(cand_p.size):
        score[k] = settings.lam * math.exp(-pairs.distance[k])
    old, edge = GatedPairs(*cached[0]), cached[1]
    if settings.use_edge:
        same = old.p.size == cand_p.size and old.leaves.size == pairs.leaves.size
        for k in range(cand_p.size if same else 0):
            same = same and old.p[k] == cand_p[k] and old.q[k] == cand_q[k]
        for k in range(pairs.leaves.size if same else 0):
            same = same and old.leaves[k] == pairs.leaves[k] and old.partner[k] == pairs.partner[k]
        if not same:
            edge = edge_similarity(land_features, box_features, pairs, settings.radius2)
        for k in range(cand_p.size):
            score[k] = score[k] + edge[k]
    cache = (pairs, edge)
    rows, row_idx, cols, col_idx, single = compact_pairs(cand_p, cand_q)
    for k in range(cand_p.size):
        single = single and score[k] > 0
    if single:
        kept = score >= settings.tau1
        return cand_p[kept], cand_q[kept], score[kept], cache
    weights = np.zeros((rows.size, cols.size))
    valid = np.zeros((rows.size, cols.size), dtype=np.bool_)
    for k in range(cand_p.size):
        weights[row_idx[k], col_idx[k]] = score[k]
        valid[row_idx[k], col_idx[k]] = True
    r, c = max_weight_assignment(weights)
    kept = np.zeros(r.size, dtype=np.bool_)
    for k in range(r.size):
        kept[k] = valid[r[k], c[k]] and weights[r[k], c[k]] >= settings.tau1
    r, c = r[kept], c[kept]
    matched = np.empty(r.size)
    for k in range(r.size):
        matched[k] = weights[r[k], c[k]]
    return rows[r], cols[c], matched, cache


@njit(cache=True)
def empty_match_cache():
    """A :func:`scored_pairs` cache that matches no later call."""
    empty = np.zeros(0, dtype=np.int64)
    return GatedPairs(empty, empty.copy(), np.zeros(0), empty.copy(), empty.copy()), np.zeros(0)


@njit(cache=True)
def _matches(pose, boxes, land_xy, world, tau2, match, cache):
    """One star-graph matching (:func:`scored_pairs`) of the :class:`AgentBoxes` under
    ``pose`` (3,) with gate ``tau2`` (m) and the :class:`MatchSettings` against the
    :class:`LandmarkMap` (centres land_xy (L, 2)): (landmark (P,), box (P,), new cache); no
    landmarks or no boxes: no matches, the cache kept."""
    if land_xy.shape[0] == 0 or boxes.poses.shape[0] == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty.copy(), cache
    land, box, _, cache = scored_pairs(land_xy, placed_centres(pose, boxes.poses), tau2,
                                       world.features, boxes.features, match, cache)
    return land, box, cache


@njit(cache=True)
def attempt_rounds(state, boxes, world, settings, match, solver):
    """RoCo's match-optimise rounds for one collaborator (``roco._attempt``) from the
    :class:`RoundState` ``state`` (to start: the first pose estimate T_{j->i}, no matches,
    no rounds): its :class:`AgentBoxes` against the :class:`LandmarkMap`, with the
    :class:`RoundSettings`, the matcher's :class:`MatchSettings` and the rounds'
    :class:`Solver` (records as plain tuples, module docstring).

    Each round matches the boxes placed by the estimate (:func:`scored_pairs`; a first
    round with fewer than min_matches matches is redone with coarse_tau2 when it is > 0);
    the rounds stop when a matching repeats the previous one, has fewer than min_matches
    pairs, or after ``rounds``. Otherwise the round solves the pose: the single vertex
    against the fixed landmarks (:func:`solve_pose_edges`: the prior edge from the reported
    pose, each edge with the information of box minus landmark, ``(own_cov +
    land_cov)^-1``, when ``difference`` (the landmark held fixed has the error of the box
    that created it), else the box's own), or, when ``joint``, the caller's joint solve of
    the whole graph: the rounds then pause before it, and the caller goes on with the
    returned state, its pose, chi2, landmarks and iterations those of the joint solve.

    When the rounds end solved with at least min_matches edges of chi2 <= inlier_chi2 and
    fit_tolerance > 0, also the significance test's statistic (:func:`wald_statistic` with
    the covariance of box minus landmark, LM stop fit_tolerance); else nan.

    Returns (:class:`RoundState` as a plain tuple, statistic, paused for a joint solve).
    """
    state, boxes, world = RoundState(*state), AgentBoxes(*boxes), LandmarkMap(*world)
    settings, match, solver = RoundSettings(*settings), MatchSettings(*match), Solver(*solver)
    land_xy = np.ascontiguousarray(world.poses[:, :2])
    pose, match_land, match_box = state.pose, state.match_land, state.match_box
    solved, chi2, landmarks = state.solved, state.chi2, state.landmarks
    outer, iterations = state.outer, state.iterations
    cache = empty_match_cache()
    while outer < settings.rounds:
        land, box, cache = _matches(pose, boxes, land_xy, world, settings.tau2, match, cache)
        if outer == 0 and land.size < settings.min_matches and settings.coarse_tau2 > 0:
            land, box, cache = _matches(pose, boxes, land_xy, world, settings.coarse_tau2, match,
                                        cache)
        if outer and _same(land, match_land) and _same(box, match_box):
            break
        outer += 1
        match_land, match_box = land, box
        solved = land.size >= settings.min_matches
        if not solved:
            break
        if settings.joint:
            # The RoundState's fields, as a plain tuple (module docstring).
            paused = (pose, match_land, match_box, solved, chi2, landmarks, outer, iterations)
            return paused, np.nan, True
        landmarks = world.poses[match_land]
        if settings.difference:
            edge_info = inverse_covariances(boxes.covariance[match_box]
                                            + world.covariance[match_land])
        else:
            edge_info = boxes.information[match_box]
        pose, chi2, _, _, solves, _ = solve_pose_edges(
            pose, landmarks, boxes.poses[match_box], edge_info,
            PriorEdge(boxes.reported, settings.prior_information), solver,
        )
        iterations += solves
    statistic = np.nan
    if (solved and settings.fit_tolerance > 0
            and np.count_nonzero(chi2 <= settings.inlier_chi2) >= settings.min_matches):
        statistic = wald_statistic(
            pose, landmarks, boxes.poses[match_box],
            boxes.covariance[match_box] + world.covariance[match_land], boxes.reported,
            Solver(solver.kernel, solver.delta, solver.max_iterations, settings.fit_tolerance,
                   solver.min_diag),
        )
    final = (pose, match_land, match_box, solved, chi2, landmarks, outer, iterations)
    return final, statistic, False


@njit(cache=True)
def _same(a, b):
    """``np.array_equal`` of two 1-d integer arrays."""
    if a.size != b.size:
        return False
    for k in range(a.size):
        if a[k] != b[k]:
            return False
    return True


@njit(cache=True)
def placed_landmarks(pose, own, boxes):
    """The agent's boxes ``own[boxes]`` (own (K, 3) in its frame, boxes (B,) indices) placed
    in the ego frame by its pose (3,) as ``geometry.se2_compose(pose, own[boxes])`` does
    (yaw wrapped to (-pi, pi]), with their pose features (5, B) (``matching.pose_features``:
    x, y, x^2 + y^2, cos(yaw), sin(yaw))."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    poses = np.empty((boxes.size, 3))
    features = np.empty((5, boxes.size))
    for k in range(boxes.size):
        bx, by, byaw = own[boxes[k], 0], own[boxes[k], 1], own[boxes[k], 2]
        x = pose[0] + c * bx - s * by
        y = pose[1] + s * bx + c * by
        yaw = (pose[2] + byaw + math.pi) % (2.0 * math.pi) - math.pi
        if yaw <= -math.pi:
            yaw += 2.0 * math.pi
        poses[k, 0], poses[k, 1], poses[k, 2] = x, y, yaw
        features[0, k], features[1, k], features[2, k] = x, y, x * x + y * y
        features[3, k], features[4, k] = math.cos(yaw), math.sin(yaw)
    return poses, features


@njit(cache=True)
def committed_map(pose, match_land, match_box, boxes, agent, landmarks, observations):
    """RoCo's map after accepting a collaborator (``roco._commit``), in one pass: its
    boxes (:class:`AgentBoxes`: poses (K, 3) in its frame,
    covariance (K, 3, 3)) matched as match_box (P,) to the landmarks match_land (P,)
    become observations, the unmatched ones (in increasing box order) new landmarks placed
    by its pose (3,) (:func:`placed_landmarks`). Returns the :class:`LandmarkMap` (M')
    and the :class:`Observations` (O') as plain tuples: the inputs with the new rows appended, as
    ``np.concatenate`` gives them (agent: the collaborator's index)."""
    boxes, landmarks = AgentBoxes(*boxes), LandmarkMap(*landmarks)
    observations = Observations(*observations)
    own, covariance = boxes.poses, boxes.covariance
    land_poses, land_features = landmarks.poses, landmarks.features
    land_covariance = landmarks.covariance
    obs_agent, obs_box, obs_land = observations.agent, observations.box, observations.land
    unmatched = np.ones(own.shape[0], dtype=np.bool_)
    for k in range(match_box.size):
        unmatched[match_box[k]] = False
    new_boxes = np.nonzero(unmatched)[0]
    n_land, n_new, n_obs = land_poses.shape[0], new_boxes.size, obs_agent.size
    new_poses, new_features = placed_landmarks(pose, own, new_boxes)
    poses = np.concatenate((land_poses, new_poses))
    features = np.empty((5, n_land + n_new))
    features[:, :n_land] = land_features
    features[:, n_land:] = new_features
    land_cov = np.empty((n_land + n_new, 3, 3))
    land_cov[:n_land] = land_covariance
    for k in range(n_new):
        land_cov[n_land + k] = covariance[new_boxes[k]]
    size = n_obs + own.shape[0]
    agents, box_ids = np.empty(size, np.int64), np.empty(size, np.int64)
    lands = np.empty(size, np.int64)
    agents[:n_obs], box_ids[:n_obs], lands[:n_obs] = obs_agent, obs_box, obs_land
    agents[n_obs:] = agent
    for k in range(match_box.size):
        box_ids[n_obs + k], lands[n_obs + k] = match_box[k], match_land[k]
    for k in range(n_new):
        box_ids[n_obs + match_box.size + k] = new_boxes[k]
        lands[n_obs + match_box.size + k] = n_land + k
    # The LandmarkMap's and the Observations' fields, as plain tuples (module docstring).
    return (poses, features, land_cov), (agents, box_ids, lands)
