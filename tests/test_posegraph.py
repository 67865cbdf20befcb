"""SE(2) pose-graph solver: residuals, Jacobians, and agreement with brute-force solvers."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import least_squares, minimize

from roco_env.geometry import se2_compose, se2_inverse, se2_relative
from roco_env.policies.posegraph import (
    PoseGraph,
    edge_residuals,
    optimize,
    optimize_pose,
    pose_hessian,
    robust_kernel,
)

pose_st = st.tuples(st.floats(-50, 50), st.floats(-50, 50), st.floats(-np.pi, np.pi)).map(np.array)


@settings(max_examples=40, deadline=None)
@given(pose_st, pose_st, pose_st)
def test_residual_is_measurement_error_and_jacobians_match_finite_differences(a, b, z):
    e, j_a, j_b = edge_residuals(a[None], b[None], z[None])
    expected = se2_compose(se2_inverse(z), se2_relative(a, b))
    assert np.allclose(e[0, :2], expected[:2], atol=1e-9)
    assert np.isclose(np.angle(np.exp(1j * (e[0, 2] - expected[2]))), 0.0, atol=1e-9)
    h = 1e-6

    def diff(plus, minus):  # central difference, angle difference wrapped
        d = plus[0] - minus[0]
        d[:, 2] = np.angle(np.exp(1j * d[:, 2]))
        return d[0] / (2 * h)

    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        num_a = diff(
            edge_residuals((a + d)[None], b[None], z[None]),
            edge_residuals((a - d)[None], b[None], z[None]),
        )
        num_b = diff(
            edge_residuals(a[None], (b + d)[None], z[None]),
            edge_residuals(a[None], (b - d)[None], z[None]),
        )
        assert np.allclose(num_a, j_a[0, :, k], atol=1e-5)
        assert np.allclose(num_b, j_b[0, :, k], atol=1e-5)


def _random_graph(seed, n_agents=3, n_landmarks=6, with_priors=True, outliers=0):
    rng = np.random.default_rng(seed)
    agents = rng.normal(size=(n_agents, 3)) * [5, 5, 0.5]
    agents[0] = 0.0
    lands = rng.normal(size=(n_landmarks, 3)) * [10, 10, 1]
    oa, ol = np.meshgrid(np.arange(n_agents), np.arange(n_landmarks), indexing="ij")
    keep = rng.random(oa.size) < 0.8
    keep[:n_landmarks] = True  # the ego sees everything: the graph is connected
    oa, ol = oa.ravel()[keep], ol.ravel()[keep]
    meas = se2_relative(agents[oa], lands[ol]) + rng.normal(size=(oa.size, 3)) * 0.05
    meas[rng.choice(oa.size, outliers, replace=False), :2] += 3.0
    sig = rng.uniform(0.05, 0.3, size=(oa.size, 3))
    info = np.zeros((oa.size, 3, 3))
    info[:, [0, 1, 2], [0, 1, 2]] = sig**-2
    prior = dict(prior_from=np.zeros(0, int), prior_to=np.zeros(0, int))
    if with_priors:
        to = np.arange(1, n_agents)
        prior = dict(
            prior_from=np.zeros(to.size, int),
            prior_to=to,
            prior_measurement=se2_relative(agents[:1], agents[to])
            + rng.normal(size=(to.size, 3)) * 0.3,
            prior_information=np.tile(np.eye(3), (to.size, 1, 1)),
        )
    init_a = agents + rng.normal(size=agents.shape) * [0.5, 0.5, 0.05]
    init_a[0] = 0.0
    init_l = lands + rng.normal(size=lands.shape) * [0.5, 0.5, 0.05]
    return PoseGraph.build(init_a, init_l, oa, ol, meas, info, **prior)


def _stacked(graph, x):
    n = graph.agents.shape[0]
    agents = np.vstack([graph.agents[:1], x[: 3 * (n - 1)].reshape(-1, 3)])
    return agents, x[3 * (n - 1) :].reshape(-1, 3)


def _whitened(graph, x):
    agents, lands = _stacked(graph, x)
    e1 = edge_residuals(agents[graph.obs_agent], lands[graph.obs_landmark], graph.obs_measurement)[
        0
    ]
    e2 = edge_residuals(agents[graph.prior_from], agents[graph.prior_to], graph.prior_measurement)[
        0
    ]
    l1 = np.linalg.cholesky(graph.obs_information).transpose(0, 2, 1)
    l2 = np.linalg.cholesky(graph.prior_information).transpose(0, 2, 1) if e2.size else l1[:0]
    return (np.einsum("eij,ej->ei", l1, e1), np.einsum("eij,ej->ei", l2, e2))


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("with_priors", [True, False])
def test_least_squares_solution_matches_dense_brute_force(seed, with_priors):
    graph = _random_graph(seed, with_priors=with_priors)
    result = optimize(graph, tolerance=1e-14)
    x0 = np.concatenate([graph.agents[1:].ravel(), graph.landmarks.ravel()])
    brute = least_squares(
        lambda x: np.concatenate([r.ravel() for r in _whitened(graph, x)]),
        x0,
        xtol=1e-15,
        ftol=1e-15,
        gtol=1e-15,
    )
    agents, lands = _stacked(graph, brute.x)
    assert result.converged and result.iterations < 1000
    assert np.isclose(result.cost, 2 * brute.cost, rtol=1e-9)
    assert np.allclose(result.agents, agents, atol=1e-6)
    assert np.allclose(result.landmarks[:, :2], lands[:, :2], atol=1e-6)
    assert np.allclose(result.agents[0], graph.agents[0])  # the fixed vertex never moves


@pytest.mark.parametrize("kernel", ["huber", "cauchy"])
def test_robust_solution_matches_brute_force_minimisation(kernel):
    graph = _random_graph(5, n_agents=3, n_landmarks=8, outliers=3)
    delta = 2.0
    result = optimize(graph, kernel=kernel, kernel_delta=delta, tolerance=1e-14)

    def cost(x):
        w1, w2 = _whitened(graph, x)
        return robust_kernel((w1**2).sum(1), kernel, delta)[0].sum() + (w2**2).sum()

    start = np.concatenate([result.agents[1:].ravel(), result.landmarks.ravel()])
    brute = minimize(cost, start + 0.01, method="BFGS", options={"gtol": 1e-10})
    assert result.cost <= brute.fun + 1e-6
    assert np.allclose(_stacked(graph, brute.x)[0], result.agents, atol=1e-4)


def test_robust_kernel_downweights_outliers():
    plain = optimize(_random_graph(7, outliers=4))
    robust = optimize(_random_graph(7, outliers=4), kernel="cauchy", kernel_delta=2.0)
    clean = optimize(_random_graph(7, outliers=0))
    err_plain = np.abs(plain.agents - clean.agents).max()
    err_robust = np.abs(robust.agents - clean.agents).max()
    assert err_robust < 0.5 * err_plain


def test_other_fixed_vertex_and_iteration_cap():
    graph = _random_graph(3)
    result = optimize(graph, fixed=2)
    assert np.allclose(result.agents[2], graph.agents[2])
    capped = optimize(graph, max_iterations=1)
    assert capped.iterations == 1 and not capped.converged and capped.cost < capped.initial_cost


def test_single_pose_solver_matches_brute_force():
    rng = np.random.default_rng(4)
    truth = np.array([3.0, -2.0, 0.4])
    lands = rng.normal(size=(6, 3)) * [15, 15, 1]
    meas = se2_relative(truth, lands) + rng.normal(size=(6, 3)) * 0.05
    info = np.tile(np.diag([100.0, 100.0, 400.0]), (6, 1, 1))
    prior, prior_info = truth + [0.5, -0.3, 0.02], np.eye(3)
    result = optimize_pose(
        truth + [0.8, 0.8, 0.05], lands, meas, info, prior, prior_info, tolerance=1e-14
    )

    def resid(x):
        e = edge_residuals(np.tile(x, (6, 1)), lands, meas)[0] * [10.0, 10.0, 20.0]
        return np.concatenate(
            [e.ravel(), edge_residuals(np.zeros((1, 3)), x[None], prior[None])[0][0]]
        )

    brute = least_squares(resid, truth, xtol=1e-15, ftol=1e-15, gtol=1e-15)
    assert np.allclose(result.pose, brute.x, atol=1e-7)
    assert np.isclose(result.cost, 2 * brute.cost, rtol=1e-8)


def test_bad_graphs_raise_value_errors_naming_the_field():
    graph = _random_graph(0)
    with pytest.raises(ValueError, match="kernel"):
        optimize(graph, kernel="tukey")
    with pytest.raises(ValueError, match="obs_landmark"):
        PoseGraph.build(
            graph.agents,
            graph.landmarks,
            graph.obs_agent,
            graph.obs_landmark + 100,
            graph.obs_measurement,
            graph.obs_information,
        )
    with pytest.raises(ValueError, match="obs_information"):
        PoseGraph.build(
            graph.agents,
            graph.landmarks,
            graph.obs_agent,
            graph.obs_landmark,
            graph.obs_measurement,
            graph.obs_information[:, :2],
        )
    with pytest.raises(ValueError, match="agents"):
        PoseGraph.build(
            np.full((2, 3), np.nan), graph.landmarks, [], [], np.zeros((0, 3)), np.zeros((0, 3, 3))
        )


@pytest.mark.parametrize("kernel", [None, "cauchy"])
def test_single_pose_linearisation_matches_the_edge_jacobians(kernel):
    """The rotated single-vertex normal equations equal sum w J^T Omega J and sum w J^T
    Omega e from edge_residuals, for full (correlated) information matrices."""
    from roco_env.policies.pose_kernels import (
        KERNEL_CODES,
        PriorEdge,
        evaluate_edges,
        normal_sums,
        pose_edges,
        prior_terms,
    )

    rng = np.random.default_rng(8)
    pose = np.array([2.0, -1.0, 2.8])
    lands = rng.normal(size=(7, 3)) * [15, 15, 2]
    meas = se2_relative(pose, lands) + rng.normal(size=(7, 3)) * [0.5, 0.5, 0.2]
    root = rng.normal(size=(7, 3, 3))
    info = root @ root.transpose(0, 2, 1) + np.eye(3)
    prior, prior_info = pose + [0.3, -0.2, 0.05], np.diag([2.0, 3.0, 50.0])
    edges = pose_edges(lands, meas, info)
    rho_sum, point = evaluate_edges(pose, edges, KERNEL_CODES[kernel], 2.0)
    hess, grad = normal_sums(pose[2], edges.info, point, point.weight, True)
    terms = prior_terms(PriorEdge(prior, prior_info))  # the solver's prior edge, as it adds it
    residual = terms.jacobian @ pose - terms.offset
    residual[2] = (residual[2] + np.pi) % (2 * np.pi) - np.pi
    cost = rho_sum + residual @ terms.information @ residual
    hess, grad = hess + terms.hessian, grad + terms.weighted.T @ residual
    e, j_a, _ = edge_residuals(np.tile(pose, (7, 1)), lands, meas)
    chi2 = np.einsum("ei,eij,ej->e", e, info, e)
    rho, weight = robust_kernel(chi2, kernel, 2.0)
    e_p, _, j_p = edge_residuals(np.zeros((1, 3)), pose[None], prior[None])
    expected_h = (
        np.einsum("e,eki,ekl,elj->ij", weight, j_a, info, j_a) + j_p[0].T @ prior_info @ j_p[0]
    )
    expected_g = np.einsum("e,eki,ekl,el->i", weight, j_a, info, e) + j_p[0].T @ prior_info @ e_p[0]
    assert np.isclose(cost, rho.sum() + e_p[0] @ prior_info @ e_p[0], rtol=1e-12)
    assert np.allclose(point.chi2, chi2, rtol=1e-10)
    assert np.allclose(hess, expected_h, rtol=1e-10, atol=1e-9)
    assert np.allclose(grad, expected_g, rtol=1e-10, atol=1e-9)


def test_pose_hessian_is_the_gauss_newton_hessian_of_the_edges():
    """pose_hessian = sum J^T Omega J from edge_residuals (no kernel, no prior), and its
    inverse is the covariance of the least-squares pose: calibrated Monte Carlo spread."""
    rng = np.random.default_rng(9)
    pose = np.array([4.0, 1.0, -0.6])
    lands = rng.normal(size=(10, 3)) * [15, 15, 2]
    root = rng.normal(size=(10, 3, 3))
    info = root @ root.transpose(0, 2, 1) + np.eye(3)
    meas = se2_relative(pose, lands)
    _, j_a, _ = edge_residuals(np.tile(pose, (10, 1)), lands, meas)
    expected = np.einsum("eki,ekl,elj->ij", j_a, info, j_a)
    assert np.allclose(pose_hessian(pose, lands, meas, info), expected, rtol=1e-10, atol=1e-9)
    covariance = np.linalg.inv(expected)
    # Residual noise with covariance Omega^-1 (small-noise regime: sigma scaled down).
    scale = 0.01
    noise_root = np.linalg.cholesky(np.linalg.inv(info))
    estimates = []
    for _ in range(300):
        noise = scale * np.einsum("eij,ej->ei", noise_root, rng.normal(size=(10, 3)))
        noisy = se2_compose(meas, noise)
        estimates.append(optimize_pose(pose, lands, noisy, info, tolerance=1e-12).pose - pose)
    spread = np.cov(np.array(estimates).T) / scale**2
    assert np.allclose(np.diag(spread), np.diag(covariance), rtol=0.25)
