"""RoCo's compiled match-optimise rounds (pose_kernels.attempt_rounds, paused for the
joint solves of ``joint_every_round``) against a Python loop of the same steps, and the
compiled box placement against numpy's.

The loop (:func:`_python_rounds`) matches with the same compiled matching
(:class:`ReferenceMatcher`, which keeps its S_edge cache between rounds in Python), solves with
``optimize_pose`` (or RoCo's joint solve) and computes the significance statistic with
``wald_statistic``: what the compiled rounds replace is the loop, its stopping rules and
bookkeeping. Matches, flags and iteration counts compare exactly; float results (poses,
chi2, landmarks, the significance statistic) to rounding (``assert_equal_to_rounding``:
numpy's exp / sin / cos / BLAS are CPU-specific SIMD versions on AVX-512 machines, an ulp
off the libm functions that numba calls)."""

import numpy as np
import pytest
from conftest import assert_equal_to_rounding

from roco_env.geometry import se2_compose
from roco_env.policies import roco
from roco_env.policies.landmarks import prepare_inputs, split_rows
from roco_env.policies.matching import MatchingParams, match_star_graphs, pose_features
from roco_env.policies.pose_kernels import (
    AgentBoxes,
    RoundState,
    compact_pairs,
    empty_match_cache,
    gated_pairs,
    placed_centres,
    scored_pairs,
    wald_statistic,
)
from roco_env.policies.posegraph import optimize_pose, solver_settings
from roco_env.policies.roco import RoCoParams
from roco_env.testing.constructed_scenes import (
    benchmark_scene,
    make_scene,
    parking_rows,
    pose_error,
)


class ReferenceMatcher:
    """The star-graph matching of one collaborator's rounds, round by round in Python (what
    the compiled rounds do in ``pose_kernels._matches``): landmarks (L, 3) in the ego frame
    and the collaborator's boxes (K, 3) in its own frame, with their pose features
    (5, L) / (5, K) (``matching.pose_features``). :meth:`match` places the boxes by a pose
    estimate T_{j->i} and matches them (``pose_kernels.scored_pairs``), reusing S_edge of
    its last call while the candidate pairs and the initial matches repeat."""

    def __init__(self, landmarks, boxes_own, params, land_features, box_features):
        self.boxes_own, self.params = boxes_own, params
        self._land_xy = np.ascontiguousarray(landmarks[:, :2], dtype=float)
        self._features = land_features, box_features
        self._settings = tuple(params.match_settings())
        pairs, edge = empty_match_cache()
        self._cache = tuple(pairs), edge

    def match(self, pose, tau2=None):
        """(landmark index (P,), box index (P,), S (P,)) under the pose (3,) with gate tau2
        (m; default ``params.tau2``), sorted by landmark; no landmarks or boxes: none."""
        if self._land_xy.shape[0] == 0 or self.boxes_own.shape[0] == 0:
            empty = np.zeros(0, dtype=np.int64)
            return empty, empty, np.zeros(0)
        land, box, score, (pairs, edge) = scored_pairs(
            self._land_xy, placed_centres(np.asarray(pose, dtype=float), self.boxes_own),
            float(self.params.tau2 if tau2 is None else tau2), *self._features, self._settings,
            self._cache)
        self._cache = tuple(pairs), edge  # plain tuples: pose_kernels' module docstring
        return land, box, score


def _scenes():
    for seed, agents, objects, error in ((0, 5, 60, 0.8), (1, 10, 200, 0.8), (2, 4, 40, 5.0),
                                         (3, 3, 30, 2.0)):
        yield benchmark_scene(np.random.default_rng(seed), agents, objects, error, error)
    rng = np.random.default_rng(5)
    lot = parking_rows(3, 30, origin=(-35.0, 0.0), jitter=(0.1, 0.1, 1.0), rng=rng)
    agents = np.array([[0.0, 3.5, 0.0], [14.0, 3.5, 0.1], [-9.0, 10.5, 3.0]])
    yield make_scene(lot, agents, [pose_error(1.6, 0.3, np.pi), pose_error(3.0, 1.0, 0.5)],
                     sensor_range=30.0, noise=(0.05, 0.05, 0.01), rng=rng)
    yield _tie_lot()


def _tie_lot():
    """Identical cars 2.5 m apart without jitter: ties that need the full assignment."""
    lot = parking_rows(2, 24, origin=(-30.0, 0.0))
    agents = np.array([[0.0, 3.5, 0.0], [14.0, 3.5, 0.1]])
    return make_scene(lot, agents, [pose_error(1.3, 0.2, 0.0)], sensor_range=30.0)


def _python_rounds(inputs, world, agent, p, start):
    """``roco._attempt`` round by round in Python: its :class:`RoundState`, statistic (None
    when not computed) and last joint solve, as ``roco._Attempt``."""
    landmarks_map = world.landmarks
    matcher = ReferenceMatcher(landmarks_map.poses, inputs.poses[agent], p,
                               landmarks_map.features, world.box_features[agent])
    empty = np.zeros(0, dtype=np.int64)
    pose, match_land, match_box = np.array(start, dtype=float), empty, empty
    solved, chi2, landmarks, outer, iterations, joint = False, None, None, 0, 0, None
    for _ in range(p.max_outer_iterations if p.iterate else 1):
        land, box, _ = matcher.match(pose)
        if not outer and land.size < p.min_matches and p.coarse_tau2 is not None:
            land, box, _ = matcher.match(pose, tau2=p.coarse_tau2)
        if outer and np.array_equal(land, match_land) and np.array_equal(box, match_box):
            break
        outer += 1
        match_land, match_box = land, box
        solved = land.size >= p.min_matches
        if not solved:
            break
        state = RoundState(pose, match_land, match_box, solved, chi2, landmarks, outer,
                           iterations)
        own = inputs.poses[agent][match_box]
        if p.joint_every_round:
            joint = roco._joint_solve(inputs, world, p, state, agent)
            solution, _, shared = joint
            pose, chi2 = solution.agents[-1], solution.obs_chi2[-own.shape[0]:]
            landmarks = solution.landmarks[np.searchsorted(shared, match_land)]
            iterations += solution.iterations
            continue
        landmarks = landmarks_map.poses[match_land]
        fit = optimize_pose(pose, landmarks, own, roco._round_information(inputs, world, agent,
                                                                          state, p),
                            inputs.reported[agent - 1], roco._prior_info(p),
                            kernel=p.robust_kernel, kernel_delta=p.kernel_delta,
                            max_iterations=p.max_solver_iterations,
                            tolerance=roco._ROUND_TOLERANCE)
        pose, chi2, iterations = fit.pose, fit.chi2, iterations + fit.iterations
    statistic = None
    if solved and p.significance and np.count_nonzero(chi2 <= p.inlier_chi2) >= p.min_matches:
        covariance = inputs.all_covariance[inputs.offsets[agent] + match_box]
        statistic = float(wald_statistic(
            pose, landmarks, inputs.poses[agent][match_box],
            covariance + landmarks_map.covariance[match_land], inputs.reported[agent - 1],
            solver_settings(p.robust_kernel, p.kernel_delta, p.max_solver_iterations,
                            roco._FIT_TOLERANCE)))
    state = RoundState(pose, match_land, match_box, solved, chi2, landmarks, outer, iterations)
    return roco._Attempt(state, statistic, joint)


def _attempts(scene, p):
    """(compiled, Python loop) attempts of every collaborator, in RoCo's order, the map
    growing with each accepted one as in roco_solve."""
    inputs = prepare_inputs(*scene.args(), p)
    covariance = split_rows(inputs.all_covariance, inputs.offsets)
    world = roco._Map(inputs, covariance[0])
    for agent in range(1, inputs.n_collaborators + 1):
        boxes = AgentBoxes(inputs.poses[agent], inputs.information[agent], covariance[agent],
                           world.box_features[agent], inputs.reported[agent - 1])
        start = inputs.reported[agent - 1]
        compiled = roco._attempt(inputs, world, agent, p, start, boxes)
        loop = _python_rounds(inputs, world, agent, p, start)
        yield compiled, loop
        if not roco._rejection(inputs, world, agent, loop, p)[0]:
            roco._commit(world, agent, loop, boxes)


PARAMS = [RoCoParams(), RoCoParams(iterate=False), RoCoParams(coarse_tau2=None),
          RoCoParams(significance=None), RoCoParams(inlier_chi2=0.5),
          RoCoParams(robust_kernel="huber"), RoCoParams(robust_kernel=None),
          RoCoParams(use_edge_similarity=False), RoCoParams(use_distance_similarity=False),
          RoCoParams(neighbor_radius=None), RoCoParams(tau2=1.0, min_matches=5),
          RoCoParams(round_information="box"), RoCoParams(joint_every_round=True),
          RoCoParams(joint_every_round=True, significance=None)]


@pytest.mark.parametrize("p", PARAMS, ids=range(len(PARAMS)))
def test_compiled_rounds_are_the_python_loop(p):
    rounded = ("pose", "chi2", "landmarks")
    compared = tested = 0
    for scene in _scenes():
        for compiled, loop in _attempts(scene, p):
            for name in RoundState._fields:
                got, expected = getattr(compiled.state, name), getattr(loop.state, name)
                if expected is None:  # no solve: the loop leaves chi2 / landmarks unset
                    assert name in ("chi2", "landmarks") and not loop.state.solved
                    continue
                assert np.asarray(got).dtype == np.asarray(expected).dtype, name
                if name in rounded:
                    assert_equal_to_rounding(got, expected, err_msg=name)
                else:
                    np.testing.assert_array_equal(got, expected, err_msg=name)
            compared += loop.state.solved
            assert (compiled.statistic is None) == (loop.statistic is None)
            if loop.statistic is not None:
                assert_equal_to_rounding(compiled.statistic, loop.statistic)
                tested += 1
            assert (compiled.joint is None) == (loop.joint is None)
            if loop.joint is not None:  # the solve a commit stores
                for got, expected in zip(compiled.joint[1:], loop.joint[1:], strict=True):
                    np.testing.assert_array_equal(got, expected)
                assert_equal_to_rounding(compiled.joint[0].landmarks, loop.joint[0].landmarks)
    assert compared >= 10 and (tested >= 5 or not p.significance)


def test_rounds_needing_the_full_assignment_stay_compiled():
    """The tie-heavy lot's first matching has landmarks with several candidate boxes: the
    compiled rounds run Kuhn-Munkres themselves, with the Python loop's result."""
    scene, p = _tie_lot(), RoCoParams()
    inputs = prepare_inputs(*scene.args(), p)
    centres = placed_centres(inputs.reported[0], inputs.poses[1])
    pairs = gated_pairs(np.ascontiguousarray(inputs.poses[0][:, :2]), centres, p.tau2)
    assert not compact_pairs(pairs.p, pairs.q)[4]
    (compiled, loop), = _attempts(scene, p)
    assert compiled.state.solved and loop.state.solved
    assert_equal_to_rounding(compiled.state.pose, loop.state.pose)
    np.testing.assert_array_equal(compiled.state.match_box, loop.state.match_box)


def test_placed_centres_are_numpys_placement_to_rounding():
    rng = np.random.default_rng(12)
    for _ in range(50):
        own = np.column_stack([rng.uniform(-80, 80, (40, 2)), rng.uniform(-3, 3, 40)])
        pose = np.array([*rng.normal(0, 20, 2), rng.uniform(-np.pi, np.pi)])
        c, s = np.cos(pose[2]), np.sin(pose[2])
        expected = own[:, :2] @ np.array([[c, s], [-s, c]]) + pose[:2]
        got = placed_centres(pose, own)
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12)
        x = own[:, 0] * c + own[:, 1] * -s + pose[0]  # the documented order
        assert_equal_to_rounding(got[:, 0], x)  # np.cos / np.sin: SIMD on AVX-512


def test_matcher_rounds_agree_with_fresh_matching():
    """The rounds' matching reuses S_edge between rounds only when candidates and initial
    matches repeat: every round must equal a from-scratch match_star_graphs call."""
    rng = np.random.default_rng(6)
    lands = np.column_stack([rng.uniform(-30, 30, (30, 2)), rng.uniform(-3, 3, 30)])
    own = se2_compose(pose_error(0.0, 20.0), lands[:25] + rng.normal(0, [0.1, 0.1, 0.02], (25, 3)))
    params = MatchingParams(tau2=4.0)
    matcher = ReferenceMatcher(lands, own, params, pose_features(lands), pose_features(own))
    truth = se2_compose(np.zeros(3), pose_error(0.0, -20.0))
    poses = [truth + np.array(error) for error in
             ([2.0, 0.0, 0.0], [0.3, 0.1, 0.0], [0.3, 0.1, 0.0], [3.5, -1.0, 0.05], [0.0] * 3)]
    gates = [None] * len(poses) + [8.0]
    sizes = []
    poses.append(truth + [5.0, 0.0, 0.0])  # the coarse gate
    for pose, tau2 in zip(poses, gates, strict=True):
        got = matcher.match(pose, tau2=tau2)
        fresh = params if tau2 is None else MatchingParams(tau2=tau2)
        expected = match_star_graphs(lands, own, se2_compose(pose, own), fresh)
        np.testing.assert_array_equal(got[0], expected[0])
        np.testing.assert_array_equal(got[1], expected[1])
        assert_equal_to_rounding(got[2], expected[2])
        sizes.append(got[0].size)
    assert min(sizes) >= 5 and max(sizes) == own.shape[0]  # every round matches, some all boxes
