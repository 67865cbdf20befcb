"""The compiled (numba) Levenberg-Marquardt loops of roco_env.policies.pose_kernels
against the array (numpy) path they replaced: the same poses, costs, per-edge chi2 and
iteration counts, on random graphs with and without priors, every kernel and another
fixed vertex, and on single-vertex problems with correlated information (the
single-vertex loop against a Python loop over the compiled linearisation,
:class:`_PoseProblem`)."""

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from roco_env.geometry import se2_relative
from roco_env.policies.pose_kernels import (
    KERNEL_CODES,
    PriorEdge,
    RefineSettings,
    damped_step,
    evaluate_edges,
    normal_sums,
    pose_edges,
    prior_terms,
    refine_pose,
    wald_statistic,
)
from roco_env.policies.posegraph import (
    _MIN_DIAG,
    PoseGraph,
    _measurement_offset,
    _residuals_jacobian,
    _wrap,
    optimize,
    optimize_pose,
    pose_hessians,
    robust_kernel,
    solver_settings,
)


def _wrap_scalar(angle):
    """``posegraph._wrap`` of one float (Python's float ``%`` is fmod with numpy's sign
    fix-up: the same value to the bit)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


class _PoseProblem:
    """One agent vertex observing fixed landmarks (and an optional prior edge from the
    fixed identity vertex), linearised by the compiled pieces (evaluate_edges, normal_sums,
    prior_terms) for the Python LM loop below: the reference of the compiled loop."""

    def __init__(self, landmarks, measurement, information, prior, prior_information, kernel,
                 delta):
        self.kernel_code, self.delta = KERNEL_CODES[kernel], float(delta)
        self.edges = pose_edges(np.asarray(landmarks, dtype=float),
                                np.asarray(measurement, dtype=float),
                                np.asarray(information, dtype=float))
        self.prior = None
        if prior is not None:
            self.prior = prior_terms(PriorEdge(np.asarray(prior, dtype=float).reshape(3),
                                               np.asarray(prior_information, dtype=float)))

    def evaluate(self, pose):
        """(robust cost, linearisation point: chi2 first) at ``pose`` (3,)."""
        rho_sum, point = evaluate_edges(np.asarray(pose, dtype=float), self.edges,
                                        self.kernel_code, self.delta)
        cost, e_p = rho_sum, None
        if self.prior is not None:
            e_p = self.prior.jacobian @ pose - self.prior.offset
            e_p[2] = _wrap_scalar(float(e_p[2]))
            cost += float(e_p @ self.prior.information @ e_p)
        return cost, (point.chi2, float(pose[2]), point, e_p)

    def normal_equations(self, point):
        """(H (3, 3), g (3,)) at a point from :meth:`evaluate`."""
        _, yaw, lin, e_p = point
        hess, grad = normal_sums(yaw, self.edges.info, lin, lin.weight, True)
        if e_p is not None:
            hess = hess + self.prior.hessian
            grad = grad + self.prior.weighted.T @ e_p
        return hess, grad


def _levenberg_marquardt(x, evaluate, normal_equations, propose, max_iterations, tolerance):
    """The array path's LM loop (lam from 1e-4, x10 on a rejected step up to 1e12, /10
    on an accepted one; relative-decrease and step-size stops)."""
    cost, lin = evaluate(x)
    initial_cost, lam, iterations, converged = cost, 1e-4, 0, False
    while iterations < max_iterations and not converged:
        iterations += 1
        system = normal_equations(lin)
        while True:
            trial_x, step = propose(x, system, lam)
            trial_cost, trial_lin = evaluate(trial_x)
            if trial_cost <= cost:
                break
            lam *= 10.0
            if lam > 1e12:
                converged = True
                break
        if converged:
            break
        decrease = cost - trial_cost
        x, cost, lin = trial_x, trial_cost, trial_lin
        lam = max(lam / 10.0, 1e-12)
        converged = decrease <= tolerance * max(cost, 1e-300) or step <= tolerance
    return x, cost, lin, initial_cost, iterations, converged


def _numpy_optimize(graph, fixed, kernel, delta, max_iterations=1000, tolerance=1e-6):
    """Whole-graph LM with dense numpy normal equations and a Schur complement."""
    na, nl = graph.agents.shape[0], graph.landmarks.shape[0]
    n_obs = graph.obs_agent.size
    from_v = np.concatenate([graph.obs_agent, graph.prior_from])
    to_v = np.concatenate([na + graph.obs_landmark, graph.prior_to])
    meas = np.concatenate([graph.obs_measurement, graph.prior_measurement])
    info = np.concatenate([graph.obs_information, graph.prior_information])
    free = np.arange(3 * na)
    free = free[(free < 3 * fixed) | (free >= 3 * fixed + 3)]

    def evaluate(x):
        e, jac = _residuals_jacobian(x[from_v], x[to_v], meas[:, 2], _measurement_offset(meas))
        chi2 = np.einsum("ei,eij,ej->e", e, info, e)
        rho, weight = robust_kernel(chi2[:n_obs], kernel, delta)
        weight = np.concatenate([weight, np.ones(chi2.size - n_obs)])
        return float(rho.sum() + chi2[n_obs:].sum()), (e, jac, chi2, weight)

    def normal_equations(lin):
        e, jac, _, weight = lin
        jt_info = np.matmul(jac.transpose(0, 2, 1), info * weight[:, None, None])
        blocks, grads = jt_info @ jac, (jt_info @ e[:, :, None])[:, :, 0]
        h = np.zeros((3 * (na + nl), 3 * (na + nl)))
        g = np.zeros(3 * (na + nl))
        for k in range(from_v.size):
            idx = np.concatenate([3 * from_v[k] + np.arange(3), 3 * to_v[k] + np.arange(3)])
            h[np.ix_(idx, idx)] += blocks[k]
            g[idx] += grads[k]
        return h, g

    def propose(x, system, lam):
        h, g = system
        damped = h + lam * np.diag(np.maximum(np.diag(h), _MIN_DIAG))
        keep = np.concatenate([free, np.arange(3 * na, 3 * (na + nl))])
        delta_x = np.zeros(3 * (na + nl))
        delta_x[keep] = np.linalg.solve(damped[np.ix_(keep, keep)], -g[keep])
        trial = x + delta_x.reshape(-1, 3)
        trial[:, 2] = _wrap(trial[:, 2])
        return trial, np.abs(delta_x).max(initial=0.0)

    start = np.concatenate([graph.agents, graph.landmarks])
    x, cost, lin, initial_cost, iterations, converged = _levenberg_marquardt(
        start, evaluate, normal_equations, propose, max_iterations, tolerance
    )
    return x, lin[2], initial_cost, cost, iterations, converged


def _graph(seed, n_agents, n_landmarks, with_priors, outliers):
    rng = np.random.default_rng(seed)
    agents = rng.normal(size=(n_agents, 3)) * [5, 5, 0.5]
    agents[0] = 0.0
    lands = rng.normal(size=(n_landmarks, 3)) * [10, 10, 1]
    oa, ol = np.meshgrid(np.arange(n_agents), np.arange(n_landmarks), indexing="ij")
    keep = rng.random(oa.size) < 0.6
    keep[:n_landmarks] = True
    oa, ol = oa.ravel()[keep], ol.ravel()[keep]
    meas = se2_relative(agents[oa], lands[ol]) + rng.normal(size=(oa.size, 3)) * 0.05
    meas[rng.choice(oa.size, outliers, replace=False), :2] += 3.0
    root = rng.normal(size=(oa.size, 3, 3)) * 0.2
    info = root @ root.transpose(0, 2, 1) + np.diag([20.0, 20.0, 100.0])
    prior = {}
    if with_priors:
        to = np.arange(1, n_agents)
        prior = dict(
            prior_from=np.zeros(to.size, int),
            prior_to=to,
            prior_measurement=se2_relative(agents[:1], agents[to])
            + rng.normal(size=(to.size, 3)) * 0.3,
            prior_information=np.tile(np.diag([1.0, 2.0, 30.0]), (to.size, 1, 1)),
        )
    init_a = agents + rng.normal(size=agents.shape) * [0.5, 0.5, 0.05]
    init_a[0] = 0.0
    init_l = lands + rng.normal(size=lands.shape) * [0.5, 0.5, 0.05]
    return PoseGraph.build(init_a, init_l, oa, ol, meas, info, **prior)


@pytest.mark.parametrize("kernel", [None, "huber", "cauchy"])
@pytest.mark.parametrize("seed", range(4))
def test_compiled_graph_solver_matches_the_numpy_path(kernel, seed):
    graph = _graph(seed, n_agents=2 + seed, n_landmarks=8 + 5 * seed, with_priors=seed % 2 == 0,
                   outliers=2)
    fixed = seed % 2  # another vertex than the ego held fixed in half the cases
    result = optimize(graph, fixed=fixed, kernel=kernel, kernel_delta=2.0)
    x, chi2, initial_cost, cost, iterations, converged = _numpy_optimize(graph, fixed, kernel, 2.0)
    na = graph.agents.shape[0]
    assert result.iterations == iterations and result.converged == converged
    np.testing.assert_allclose(result.agents, x[:na], rtol=0, atol=1e-9)
    np.testing.assert_allclose(result.landmarks, x[na:], rtol=0, atol=1e-9)
    np.testing.assert_allclose(result.obs_chi2, chi2[: graph.obs_agent.size], rtol=1e-9,
                               atol=1e-12)
    np.testing.assert_allclose(result.prior_chi2, chi2[graph.obs_agent.size :], rtol=1e-9,
                               atol=1e-12)
    assert np.isclose(result.initial_cost, initial_cost, rtol=1e-12)
    assert np.isclose(result.cost, cost, rtol=1e-12)
    np.testing.assert_allclose(result.agents[fixed], graph.agents[fixed], rtol=0, atol=1e-12)


def test_compiled_graph_solver_respects_the_iteration_cap():
    graph = _graph(7, n_agents=4, n_landmarks=12, with_priors=True, outliers=0)
    capped = optimize(graph, max_iterations=2)
    x = _numpy_optimize(graph, 0, None, 1.0, max_iterations=2)[0]
    assert capped.iterations == 2 and not capped.converged
    np.testing.assert_allclose(capped.agents, x[:4], rtol=0, atol=1e-9)


@pytest.mark.parametrize("kernel", [None, "huber", "cauchy"])
@pytest.mark.parametrize("with_prior", [False, True])
def test_compiled_single_pose_solver_matches_the_numpy_path(kernel, with_prior):
    rng = np.random.default_rng(11)
    truth = np.array([3.0, -2.0, 2.9])
    lands = rng.normal(size=(25, 3)) * [15, 15, 2]
    meas = se2_relative(truth, lands) + rng.normal(size=(25, 3)) * [0.1, 0.1, 0.02]
    meas[:4, :2] += 2.5  # outliers
    root = rng.normal(size=(25, 3, 3))
    info = root @ root.transpose(0, 2, 1) + np.eye(3)
    prior = (truth + [0.5, -0.3, 0.02], np.diag([2.0, 3.0, 50.0])) if with_prior else (None, None)
    start = truth + [0.8, -0.6, 0.1]
    result = optimize_pose(start, lands, meas, info, *prior, kernel=kernel, kernel_delta=2.0)
    problem = _PoseProblem(lands, meas, info, *prior, kernel, 2.0)

    def propose(pose, system, lam):
        delta, step = damped_step(*system, lam, _MIN_DIAG)
        trial = pose + delta
        trial[2] = _wrap_scalar(float(trial[2]))
        return trial, step

    pose, cost, lin, initial_cost, iterations, converged = _levenberg_marquardt(
        start.copy(), problem.evaluate, problem.normal_equations, propose, 1000, 1e-6
    )
    assert result.iterations == iterations and result.converged == converged
    np.testing.assert_allclose(result.pose, pose, rtol=0, atol=1e-12)
    np.testing.assert_allclose(result.chi2, lin[0], rtol=1e-12, atol=1e-12)
    assert np.isclose(result.cost, cost, rtol=1e-12)
    assert np.isclose(result.initial_cost, initial_cost, rtol=1e-12)


@pytest.mark.parametrize("kernel", [None, "huber", "cauchy"])
def test_compiled_wald_statistic_matches_the_numpy_path(kernel):
    """The robust sandwich statistic d^T A B^-1 A d from optimize_pose, robust_kernel,
    pose_hessians and numpy's inverse and solve."""
    rng = np.random.default_rng(12)
    for trial in range(5):
        truth = rng.normal(size=3) * [4.0, 4.0, 0.2]
        lands = rng.normal(size=(30, 3)) * [20, 20, 2]
        own = se2_relative(truth, lands) + rng.normal(size=(30, 3)) * [0.1, 0.1, 0.01]
        own[:3, :2] += 2.0  # outliers
        root = rng.normal(size=(30, 3, 3)) * 0.1
        covariance = root @ root.transpose(0, 2, 1) + np.diag([0.02, 0.03, 1e-4])
        reported = truth + rng.normal(size=3) * [0.3, 0.3, 0.01] * trial
        start = truth + [0.2, -0.1, 0.01]
        info = np.linalg.inv(covariance)
        fit = optimize_pose(start, lands, own, info, kernel=kernel, kernel_delta=2.0)
        weight = robust_kernel(fit.chi2, kernel, 2.0)[1][:, None, None]
        bread, meat = pose_hessians(fit.pose, lands, own, (info * weight, info * weight**2))
        d = fit.pose - reported
        d[2] = _wrap_scalar(float(d[2]))
        expected = (bread @ d) @ np.linalg.solve(meat, bread @ d)
        statistic = wald_statistic(start, lands, own, covariance, reported,
                                   solver_settings(kernel, 2.0, 1000, 1e-6))
        assert np.isclose(statistic, expected, rtol=1e-9, atol=1e-9)


def _tree_nearest(lands, x, y, gate):
    """(box indices, their nearest landmark) within the gate, by a k-d tree."""
    distance, nearest = cKDTree(lands[:, :2]).query(np.column_stack([x, y]),
                                                   distance_upper_bound=gate)
    box = np.nonzero(np.isfinite(distance))[0]
    return box, nearest[box]


def _dense_nearest(lands, x, y, gate):
    """:func:`_tree_nearest` by a dense scan: the lowest index among equal distances, the
    pairing rule of the compiled loop."""
    distance = np.sqrt((lands[None, :, 0] - x[:, None]) ** 2 + (lands[None, :, 1] - y[:, None]) ** 2)
    nearest = np.argmin(distance, axis=1)
    box = np.nonzero(distance[np.arange(x.size), nearest] < gate)[0]
    return box, nearest[box]


def _numpy_refine(initial, lands, own, info, gate, kernel, min_matches, pairing=_tree_nearest):
    """The array path of the hypothesis refinement: nearest centres within the gate
    (``pairing``), optimize_pose, twice (the second round only when the pairs changed)."""
    pose, previous = np.asarray(initial, dtype=float), None
    for _ in range(2):
        c, s = np.cos(pose[2]), np.sin(pose[2])
        box, land = pairing(lands, c * own[:, 0] - s * own[:, 1] + pose[0],
                            s * own[:, 0] + c * own[:, 1] + pose[1], gate)
        if box.size < min_matches:
            return None
        if previous is not None and np.array_equal(land, previous[0]) and np.array_equal(
                box, previous[1]):
            break
        previous = (land, box)
        pose = optimize_pose(pose, lands[land], own[box], info[box], kernel=kernel,
                             kernel_delta=2.0, max_iterations=50, tolerance=1e-4).pose
    return pose


@pytest.mark.parametrize("kernel", [None, "cauchy"])
def test_compiled_refinement_matches_the_numpy_path(kernel):
    rng = np.random.default_rng(13)
    for trial in range(20):
        truth = rng.normal(size=3) * [3.0, 3.0, 0.05]
        lands = np.column_stack([rng.uniform(-40, 40, (50, 2)), rng.uniform(-3, 3, 50)])
        seen = rng.choice(50, 30, replace=False)
        own = se2_relative(truth, lands[seen]) + rng.normal(size=(30, 3)) * [0.2, 0.2, 0.02]
        root = rng.normal(size=(30, 3, 3)) * 0.3
        info = root @ root.transpose(0, 2, 1) + np.diag([25.0, 25.0, 400.0])
        start = truth + rng.normal(size=3) * [0.6, 0.6, 0.01]
        gate, min_matches = 1.0, 3 if trial % 4 else 40  # every 4th: too few matches
        expected = _numpy_refine(start, lands, own, info, gate, kernel, min_matches)
        pose, ok = refine_pose(start, lands, own, info, RefineSettings(
            gate, min_matches, solver_settings(kernel, 2.0, 50, 1e-4)))
        assert ok == (expected is not None)
        if ok:
            np.testing.assert_allclose(pose, expected, rtol=0, atol=1e-9)


def test_compiled_refinement_pairs_ties_with_the_lowest_index():
    """Landmarks doubled at the same centres (other headings, higher indices) and rows at
    the same x: the windowed nearest search keeps the dense scan's choice."""
    rng = np.random.default_rng(31)
    for _ in range(20):
        truth = rng.normal(size=3) * [3.0, 3.0, 0.05]
        lands = np.column_stack([rng.uniform(-40, 40, (60, 2)), rng.uniform(-3, 3, 60)])
        lands[:20, 0] = np.round(lands[:20, 0])  # shared x values
        seen = rng.choice(60, 30, replace=False)
        own = se2_relative(truth, lands[seen]) + rng.normal(size=(30, 3)) * [0.2, 0.2, 0.02]
        twins = lands[seen[:10]].copy()
        twins[:, 2] += 0.3
        lands = np.vstack([lands, twins])
        order = rng.permutation(lands.shape[0])  # twins before or after the originals
        lands = lands[order]
        info = np.tile(np.diag([25.0, 25.0, 400.0]), (30, 1, 1))
        start = truth + rng.normal(size=3) * [0.3, 0.3, 0.01]
        expected = _numpy_refine(start, lands, own, info, 1.0, "cauchy", 3, _dense_nearest)
        pose, ok = refine_pose(start, lands, own, info, RefineSettings(
            1.0, 3, solver_settings("cauchy", 2.0, 50, 1e-4)))
        assert ok == (expected is not None)
        if ok:
            np.testing.assert_allclose(pose, expected, rtol=0, atol=1e-9)
