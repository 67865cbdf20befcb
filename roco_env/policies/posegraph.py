"""SE(2) pose-graph optimisation: agents + landmarks, Levenberg-Marquardt, Schur complement.

Vertices are SE(2) poses (x m, y m, yaw rad) in one common frame (the ego's
reported frame for the alignment policies). Two kinds of edges:

* observation edge agent a -> landmark l, measurement ``Z`` = the landmark's
  pose in the agent's frame (a detected box), 3x3 information ``Omega``;
* prior edge agent a -> agent b, measurement ``Z`` = the relative pose
  ``T_a^{-1} T_b`` (e.g. from the reported poses), 3x3 information.

Every edge has the residual of the paper's ``e_ik = T_ip^{-1} E_i^{-1} X_k``:
``e = (dx, dy, wrap(dyaw))`` of ``Z^{-1} T_a^{-1} T_l``, i.e. the translation
part ``R_z^T (R_a^T (t_l - t_a) - t_z)`` and the wrapped angle ``th_l - th_a - th_z``.
The cost is ``sum rho(e^T Omega e)`` with ``rho`` the identity (least squares)
or a Huber/Cauchy kernel on observation edges, handled by IRLS weights
``rho'(chi2)`` inside LM. Prior edges are always quadratic.

Hand-written rather than scipy.optimize.least_squares because the structure
matters: each landmark touches only agents, so its 3x3 block is eliminated by
the Schur complement and every LM step solves a 3(N-1) system (N agents, one
fixed), which is what makes per-frame alignment take milliseconds.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from roco_env.policies.pose_kernels import (
    KERNEL_CODES,
    GraphEdges,
    PriorEdge,
    Solver,
    evaluate_edges,
    normal_sums,
    pose_edges,
    solve_graph,
    solve_pose_edges,
)

__all__ = [
    "PoseGraph",
    "PoseGraphResult",
    "PoseResult",
    "ROBUST_KERNELS",
    "edge_chi2",
    "edge_residuals",
    "optimize",
    "optimize_pose",
    "pose_hessian",
    "pose_hessians",
    "robust_kernel",
    "solver_settings",
]

ROBUST_KERNELS = ("huber", "cauchy")
_MIN_DIAG = 1e-9  # keeps Marquardt damping positive for vertices with no constraint


@lru_cache(maxsize=64)
def solver_settings(
    kernel: str | None, kernel_delta: float, max_iterations: int, tolerance: float
) -> Solver:
    """The compiled solvers' :class:`~roco_env.policies.pose_kernels.Solver` record:
    kernel None (least squares), "huber" or "cauchy" with its width kernel_delta (whitened
    units), the cap on linearisations and the stop tolerance (:func:`optimize`); built
    once per setting."""
    return Solver(KERNEL_CODES[kernel], float(kernel_delta), int(max_iterations),
                  float(tolerance), _MIN_DIAG)


@dataclass(frozen=True)
class PoseGraph:
    """An SE(2) pose graph.

    agents (N, 3), landmarks (M, 3): initial vertex poses (x m, y m, yaw rad).
    obs_agent, obs_landmark (E,): vertex indices of each observation edge;
    obs_measurement (E, 3): landmark pose in the agent's frame; obs_information (E, 3, 3).
    prior_from, prior_to (P,): agent indices; prior_measurement (P, 3): T_from^{-1} T_to;
    prior_information (P, 3, 3).
    """

    agents: np.ndarray
    landmarks: np.ndarray
    obs_agent: np.ndarray
    obs_landmark: np.ndarray
    obs_measurement: np.ndarray
    obs_information: np.ndarray
    prior_from: np.ndarray
    prior_to: np.ndarray
    prior_measurement: np.ndarray
    prior_information: np.ndarray

    @classmethod
    def build(
        cls,
        agents: np.ndarray,
        landmarks: np.ndarray,
        obs_agent: np.ndarray,
        obs_landmark: np.ndarray,
        obs_measurement: np.ndarray,
        obs_information: np.ndarray,
        prior_from: np.ndarray | None = None,
        prior_to: np.ndarray | None = None,
        prior_measurement: np.ndarray | None = None,
        prior_information: np.ndarray | None = None,
    ) -> PoseGraph:
        """Validate shapes and indices and return the graph (float64/int64 arrays)."""
        agents = _poses(agents, "agents")
        landmarks = _poses(landmarks, "landmarks")
        obs_agent = _indices(obs_agent, "obs_agent", agents.shape[0])
        obs_landmark = _indices(obs_landmark, "obs_landmark", landmarks.shape[0])
        n_obs = obs_agent.size
        if obs_landmark.size != n_obs:
            raise ValueError("obs_landmark must have one entry per obs_agent entry")
        obs_measurement = _poses(obs_measurement, "obs_measurement", n_obs)
        obs_information = _information(obs_information, "obs_information", n_obs)
        prior_from = _indices(_or_empty(prior_from, (0,)), "prior_from", agents.shape[0])
        prior_to = _indices(_or_empty(prior_to, (0,)), "prior_to", agents.shape[0])
        n_prior = prior_from.size
        if prior_to.size != n_prior:
            raise ValueError("prior_to must have one entry per prior_from entry")
        prior_measurement = _poses(
            _or_empty(prior_measurement, (0, 3)), "prior_measurement", n_prior
        )
        prior_information = _information(
            _or_empty(prior_information, (0, 3, 3)), "prior_information", n_prior
        )
        return cls(
            agents,
            landmarks,
            obs_agent,
            obs_landmark,
            obs_measurement,
            obs_information,
            prior_from,
            prior_to,
            prior_measurement,
            prior_information,
        )


@dataclass(frozen=True)
class PoseGraphResult:
    """Optimised vertices and solver diagnostics.

    agents (N, 3), landmarks (M, 3): optimised poses. obs_chi2 (E,), prior_chi2 (P,):
    ``e^T Omega e`` per edge at the solution. initial_cost / cost: robust cost before
    and after. iterations: LM iterations (linearisations); converged: a convergence
    test fired before the iteration cap.
    """

    agents: np.ndarray
    landmarks: np.ndarray
    obs_chi2: np.ndarray
    prior_chi2: np.ndarray
    initial_cost: float
    cost: float
    iterations: int
    converged: bool


def _or_empty(value: np.ndarray | None, shape: tuple[int, ...]) -> np.ndarray:
    return np.zeros(shape) if value is None else value


def _poses(value: np.ndarray, name: str, count: int | None = None) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.size == 0:
        arr = arr.reshape(0, 3)
    if arr.ndim != 2 or arr.shape[1] != 3 or (count is not None and arr.shape[0] != count):
        want = f"({count}, 3)" if count is not None else "(n, 3)"
        raise ValueError(f"{name} must have shape {want} = (x, y, yaw); got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf; all values must be finite")
    return arr


def _indices(value: np.ndarray, name: str, bound: int) -> np.ndarray:
    arr = np.asarray(value).reshape(-1)
    if arr.size and (
        not np.issubdtype(arr.dtype, np.integer) or arr.min() < 0 or arr.max() >= bound
    ):
        raise ValueError(f"{name} must hold integer indices in [0, {bound}); got {arr}")
    return arr.astype(np.int64)


def _information(value: np.ndarray, name: str, count: int) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.size == 0:
        arr = arr.reshape(0, 3, 3)
    if arr.shape != (count, 3, 3):
        raise ValueError(f"{name} must have shape ({count}, 3, 3); got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf; all values must be finite")
    return arr


def edge_residuals(
    pose_a: np.ndarray, pose_b: np.ndarray, measurement: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Residuals and analytic Jacobians of ``Z^{-1} T_a^{-1} T_b`` for E edges.

    pose_a, pose_b, measurement: (E, 3). Returns e (E, 3) = (dx, dy, wrapped dyaw),
    J_a (E, 3, 3) = de/d(x_a, y_a, yaw_a) and J_b (E, 3, 3) = de/d(x_b, y_b, yaw_b).
    """
    e, jac = _residuals_jacobian(
        pose_a, pose_b, measurement[:, 2], _measurement_offset(measurement)
    )
    return e, jac[:, :, :3], jac[:, :, 3:]


def _measurement_offset(measurement: np.ndarray) -> np.ndarray:
    """R_z^T t_z (E, 2) of measurements (E, 3): the constant part of the residual."""
    cz, sz = np.cos(measurement[:, 2]), np.sin(measurement[:, 2])
    return np.stack(
        [
            cz * measurement[:, 0] + sz * measurement[:, 1],
            -sz * measurement[:, 0] + cz * measurement[:, 1],
        ],
        axis=1,
    )


def _residuals(
    pose_a: np.ndarray, pose_b: np.ndarray, meas_yaw: np.ndarray, meas_offset: np.ndarray
) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
    """e (E, 3) of ``Z^{-1} T_a^{-1} T_b`` and the terms (c, s, w_x, w_y) its Jacobian reuses."""
    angle = pose_a[:, 2] + meas_yaw
    c, s = np.cos(angle), np.sin(angle)
    dx = pose_b[:, 0] - pose_a[:, 0]
    dy = pose_b[:, 1] - pose_a[:, 1]
    # B = R(-(yaw_a + yaw_z)); w = B (t_b - t_a); e_t = w - R_z^T t_z.
    wx = c * dx + s * dy
    wy = -s * dx + c * dy
    e = np.empty((pose_a.shape[0], 3))
    e[:, 0] = wx - meas_offset[:, 0]
    e[:, 1] = wy - meas_offset[:, 1]
    e[:, 2] = _wrap(pose_b[:, 2] - angle)
    return e, (c, s, wx, wy)


def _residuals_jacobian(
    pose_a: np.ndarray, pose_b: np.ndarray, meas_yaw: np.ndarray, meas_offset: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """e (E, 3) and the stacked Jacobian (E, 3, 6) = [J_a | J_b] (see :func:`edge_residuals`)."""
    e, (c, s, wx, wy) = _residuals(pose_a, pose_b, meas_yaw, meas_offset)
    jac = np.zeros((pose_a.shape[0], 3, 6))
    jac[:, 0, 3], jac[:, 0, 4] = c, s
    jac[:, 1, 3], jac[:, 1, 4] = -s, c
    jac[:, 2, 5] = 1.0
    jac[:, :, :3] = -jac[:, :, 3:]
    # d w / d yaw_a = -S w with S the 90-degree rotation: (w_y, -w_x).
    jac[:, 0, 2] = wy
    jac[:, 1, 2] = -wx
    return e, jac


def edge_chi2(
    pose_a: np.ndarray, pose_b: np.ndarray, measurement: np.ndarray, information: np.ndarray
) -> np.ndarray:
    """``e^T Omega e`` (E,) of the edges of :func:`edge_residuals` (information (E, 3, 3))."""
    e = _residuals(pose_a, pose_b, measurement[:, 2], _measurement_offset(measurement))[0]
    return np.einsum("ei,ei->e", e, np.matmul(information, e[:, :, None])[:, :, 0])


def robust_kernel(
    chi2: np.ndarray, kernel: str | None, delta: float
) -> tuple[np.ndarray, np.ndarray]:
    """(rho(chi2), rho'(chi2)) for the robust kernel (delta in whitened units)."""
    if kernel is None:
        return chi2, np.ones_like(chi2)
    d2 = delta * delta
    if kernel == "huber":
        root = np.sqrt(chi2)
        inlier = chi2 <= d2
        rho = np.where(inlier, chi2, 2.0 * delta * root - d2)
        return rho, np.where(inlier, 1.0, delta / np.maximum(root, 1e-300))
    ratio = chi2 / d2
    return d2 * np.log1p(ratio), 1.0 / (1.0 + ratio)


def _wrap(angle: np.ndarray) -> np.ndarray:
    """Wrap to [-pi, pi) (cheaper than geometry.wrap_angle; the end point is irrelevant
    to residuals and retractions)."""
    return np.mod(angle + np.pi, 2.0 * np.pi) - np.pi


def optimize(
    graph: PoseGraph,
    fixed: int = 0,
    kernel: str | None = None,
    kernel_delta: float = 1.0,
    max_iterations: int = 1000,
    tolerance: float = 1e-6,
) -> PoseGraphResult:
    """Levenberg-Marquardt on the pose graph with agent ``fixed`` held at its initial pose.

    kernel: None (least squares), "huber" or "cauchy"; kernel_delta is the kernel
    width in whitened units (sqrt of chi2). Stops after ``max_iterations``
    linearisations, when the relative cost decrease of an accepted step falls below
    ``tolerance``, when the largest step component is below ``tolerance``, or when
    no damping yields a decrease (no progress).
    """
    if kernel is not None and kernel not in ROBUST_KERNELS:
        raise ValueError(f"kernel must be None or one of {ROBUST_KERNELS}; got {kernel!r}")
    if not kernel_delta > 0:
        raise ValueError(f"kernel_delta must be > 0; got {kernel_delta}")
    if not 0 <= fixed < max(graph.agents.shape[0], 1):
        raise ValueError(f"fixed must index an agent in [0, {graph.agents.shape[0]}); got {fixed}")
    if max_iterations < 0:
        raise ValueError(f"max_iterations must be >= 0; got {max_iterations}")
    na = graph.agents.shape[0]
    free = np.arange(3 * na)
    free = free[(free < 3 * fixed) | (free >= 3 * fixed + 3)]
    meas = np.concatenate([graph.obs_measurement, graph.prior_measurement])
    n_obs = graph.obs_agent.size
    edges = GraphEdges(
        na,
        n_obs,
        np.concatenate([graph.obs_agent, graph.prior_from]),
        np.concatenate([graph.obs_landmark, graph.prior_to]),
        np.ascontiguousarray(meas[:, 2]),
        _measurement_offset(meas),
        np.concatenate([graph.obs_information, graph.prior_information]),
    )
    x, chi2, initial_cost, cost, iterations, converged = solve_graph(
        np.concatenate([graph.agents, graph.landmarks]), tuple(edges), free,
        tuple(solver_settings(kernel, kernel_delta, max_iterations, tolerance)),
    )
    return PoseGraphResult(
        x[:na], x[na:], chi2[:n_obs], chi2[n_obs:], initial_cost, cost, iterations, converged
    )


@dataclass(frozen=True)
class PoseResult:
    """One optimised SE(2) vertex: pose (3,), chi2 (E,) of its observation edges,
    initial_cost / cost, iterations, converged (as in :class:`PoseGraphResult`)."""

    pose: np.ndarray
    chi2: np.ndarray
    initial_cost: float
    cost: float
    iterations: int
    converged: bool


def optimize_pose(
    initial: np.ndarray,
    landmarks: np.ndarray,
    measurement: np.ndarray,
    information: np.ndarray,
    prior: np.ndarray | None = None,
    prior_information: np.ndarray | None = None,
    kernel: str | None = None,
    kernel_delta: float = 1.0,
    max_iterations: int = 1000,
    tolerance: float = 1e-6,
) -> PoseResult:
    """The pose graph restricted to one agent vertex with every other vertex fixed.

    The agent (initial (3,)) observes fixed landmarks (E, 3) (same frame) with
    measurements (E, 3) and information (E, 3, 3); an optional prior edge from a fixed
    identity vertex (the ego) measures ``prior`` (3,) with ``prior_information``.
    Same residuals, kernel and LM stopping rules as :func:`optimize`, with a 3x3 system.
    """
    if kernel is not None and kernel not in ROBUST_KERNELS:
        raise ValueError(f"kernel must be None or one of {ROBUST_KERNELS}; got {kernel!r}")
    no_prior = prior is None  # a zero-information prior edge changes nothing
    pose, chi2, initial_cost, cost, iterations, converged = solve_pose_edges(
        np.asarray(initial, dtype=float).reshape(3).copy(),
        np.asarray(landmarks, dtype=float),
        np.asarray(measurement, dtype=float),
        np.asarray(information, dtype=float),
        tuple(PriorEdge(
            np.zeros(3) if no_prior else np.asarray(prior, dtype=float).reshape(3),
            np.zeros((3, 3)) if no_prior
            else np.asarray(prior_information, dtype=float).reshape(3, 3),
        )),
        tuple(solver_settings(kernel, kernel_delta, max_iterations, tolerance)),
    )
    return PoseResult(pose, chi2, initial_cost, cost, iterations, converged)


def pose_hessian(
    pose: np.ndarray, landmarks: np.ndarray, measurement: np.ndarray, information: np.ndarray
) -> np.ndarray:
    """Gauss-Newton Hessian ``sum J^T Omega J`` (3, 3) of one agent vertex at ``pose`` (3,)
    over observation edges to fixed landmarks (E, 3) (measurements (E, 3), information
    (E, 3, 3); no kernel, no prior), w.r.t. (x m, y m, yaw rad) as :func:`optimize_pose`
    moves them. Scale ``information`` per edge to weight edges (e.g. by IRLS weights).
    """
    return pose_hessians(pose, landmarks, measurement, (information,))[0]


def pose_hessians(
    pose: np.ndarray,
    landmarks: np.ndarray,
    measurement: np.ndarray,
    informations: tuple[np.ndarray, ...],
) -> list[np.ndarray]:
    """:func:`pose_hessian` for several per-edge informations (each (E, 3, 3)) at one pose
    over the same edges (e.g. a robust sandwich's bread and meat): the geometry is shared,
    each Hessian is computed exactly as :func:`pose_hessian` computes it (one pass over the
    edges, :func:`~roco_env.policies.pose_kernels.normal_sums`: with ``H = Q (sum N^T
    Omega' N) Q^T``, ``Q = blockdiag(R(yaw), 1)``, ``N = I + m e3^T`` from the landmark
    offsets in the agent's frame and ``Omega' = C^T Omega C`` the information rotated
    into the residual frame, ``C = blockdiag(R(-yaw_z), 1)``)."""
    pose = np.asarray(pose, dtype=float).reshape(3)
    landmarks = np.asarray(landmarks, dtype=float)
    measurement = np.asarray(measurement, dtype=float)
    hessians = []
    point = None
    for information in informations:
        edges = pose_edges(landmarks, measurement, np.asarray(information, dtype=float))
        if point is None:
            # The point's chi2 / info_e depend on the information, but the Hessian does not
            # use them, and the weights are ones (no kernel).
            point = evaluate_edges(pose, tuple(edges), KERNEL_CODES[None], 1.0)[1]
        hessians.append(normal_sums(pose[2], edges.info, tuple(point), point.weight, False)[0])
    return hessians
