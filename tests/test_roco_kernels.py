"""RoCo's compiled matching rounds (pose_kernels.attempt_rounds) against the Python loop
they replace (roco._attempt_loop), and the compiled box placement against numpy's.

Matches, flags and iteration counts compare exactly; float results (poses, chi2,
landmarks, the significance statistic) to rounding (``assert_equal_to_rounding``: numpy's
exp / sin / cos / BLAS are CPU-specific SIMD versions on AVX-512 machines, an ulp off the
libm functions that numba calls)."""

import numpy as np
import pytest
from conftest import assert_equal_to_rounding

from roco_env.policies import roco
from roco_env.policies.landmarks import prepare_inputs, split_rows
from roco_env.policies.pose_kernels import placed_centres
from roco_env.policies.roco import RoCoParams
from roco_env.testing.constructed_scenes import (
    benchmark_scene,
    make_scene,
    parking_rows,
    pose_error,
)


def _scenes():
    for seed, agents, objects, error in ((0, 5, 60, 0.8), (1, 10, 200, 0.8), (2, 4, 40, 5.0),
                                         (3, 3, 30, 2.0)):
        yield benchmark_scene(np.random.default_rng(seed), agents, objects, error, error)
    rng = np.random.default_rng(5)
    lot = parking_rows(3, 30, origin=(-35.0, 0.0), jitter=(0.1, 0.1, 1.0), rng=rng)
    agents = np.array([[0.0, 3.5, 0.0], [14.0, 3.5, 0.1], [-9.0, 10.5, 3.0]])
    yield make_scene(lot, agents, [pose_error(1.6, 0.3, np.pi), pose_error(3.0, 1.0, 0.5)],
                     sensor_range=30.0, noise=(0.05, 0.05, 0.01), rng=rng)
    # Identical cars 2.5 m apart without jitter: ties that need the full assignment.
    lot = parking_rows(2, 24, origin=(-30.0, 0.0))
    yield make_scene(lot, agents[:2], [pose_error(1.3, 0.2, 0.0)], sensor_range=30.0)


def _attempts(scene, p, monkeypatch):
    """(compiled, Python loop, whether the compiled one handed over to the loop, its
    arguments) attempts of every collaborator, in RoCo's order, the map growing with each
    accepted one as in roco_solve."""
    handovers = []
    python_loop = roco._attempt_loop
    monkeypatch.setattr(roco, "_attempt_loop", lambda *a: handovers.append(a) or python_loop(*a))
    inputs = prepare_inputs(*scene.args(), p)
    covariance = split_rows(inputs.all_covariance, inputs.offsets)
    world = roco._Map(inputs, covariance[0])
    for agent in range(1, inputs.n_collaborators + 1):
        start = inputs.reported[agent - 1]
        handovers.clear()
        compiled = roco._attempt(inputs, world, agent, p, start, covariance)
        handed_over = bool(handovers)
        loop = python_loop(inputs, world, agent, p, np.array(start, dtype=float))
        yield compiled, loop, handed_over, (inputs, world, agent, covariance)
        if not roco._rejection(inputs, world, agent, loop, p, covariance):
            roco._commit(inputs, world, agent, loop, covariance[agent])


PARAMS = [RoCoParams(), RoCoParams(iterate=False), RoCoParams(coarse_tau2=None),
          RoCoParams(significance=None), RoCoParams(inlier_chi2=0.5),
          RoCoParams(robust_kernel="huber"), RoCoParams(robust_kernel=None),
          RoCoParams(use_edge_similarity=False), RoCoParams(use_distance_similarity=False),
          RoCoParams(neighbor_radius=None), RoCoParams(tau2=1.0, min_matches=5),
          RoCoParams(round_information="box")]


@pytest.mark.parametrize("p", PARAMS, ids=range(len(PARAMS)))
def test_compiled_rounds_are_the_python_loop(p, monkeypatch):
    fields = ("pose", "match_land", "match_box", "solved", "chi2", "landmarks", "outer", "solver")
    rounded = ("pose", "chi2", "landmarks")
    compared = tested = 0
    for scene in _scenes():
        for compiled, loop, handed_over, args in _attempts(scene, p, monkeypatch):
            for name in fields:
                got, expected = getattr(compiled, name), getattr(loop, name)
                if expected is None:  # no solve: the loop leaves chi2 / landmarks unset
                    assert name in ("chi2", "landmarks") and not loop.solved
                    continue
                assert np.asarray(got).dtype == np.asarray(expected).dtype, name
                if name in rounded:
                    assert_equal_to_rounding(got, expected, err_msg=name)
                else:
                    np.testing.assert_array_equal(got, expected, err_msg=name)
            compared += loop.solved
            # The significance statistic, computed by the compiled rounds when the test runs.
            inliers = loop.solved and np.count_nonzero(loop.chi2 <= p.inlier_chi2) >= p.min_matches
            if inliers and p.significance and not handed_over:
                assert_equal_to_rounding(compiled.statistic,
                                         roco._correction_statistic(*args[:3], loop, p, args[3]))
                tested += 1
            else:
                assert compiled.statistic is None
    assert compared >= 10 and (tested >= 5 or not p.significance)


def test_rounds_needing_the_full_assignment_run_the_python_loop(monkeypatch):
    """The tie-heavy lot needs Kuhn-Munkres: the compiled rounds hand over to the loop."""
    scene = list(_scenes())[-1]
    handed_over = []
    for compiled, expected, handover, _ in _attempts(scene, RoCoParams(), monkeypatch):
        assert_equal_to_rounding(compiled.pose, expected.pose)
        handed_over.append(handover)
    assert handed_over == [True]


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
