"""Temporal smoothing wrapper: Kalman tracking of corrections per collaborator."""

import numpy as np
import pytest

from roco_env.policies.base import AlignmentResult
from roco_env.policies.temporal import TemporalSmoothing


def observation(n_slots=2, filled=2):
    mask = np.zeros(n_slots, np.int8)
    mask[:filled] = 1
    return {"collab_mask": mask}


def info(filled=2):
    """The env's info of ego cav_0 with ``filled`` collaborators."""
    return {"agent": "cav_0", "collaborators": [f"cav_{j + 1}" for j in range(filled)]}


class Scripted:
    """Inner policy replaying (action, applied) pairs and exposing last_result."""

    def __init__(self, steps):
        self.steps, self.t, self.last_result, self.resets = list(steps), 0, None, 0

    def __call__(self, obs, info=None):
        action, applied = self.steps[self.t]
        self.t += 1
        self.last_result = AlignmentResult(np.zeros_like(action), np.asarray(applied, bool))
        return np.asarray(action, np.float32)

    def reset(self):
        self.resets += 1


def test_frames_without_evidence_inherit_the_last_good_estimate():
    good = np.array([[0.5, -0.2, 0.01], [0.0, 0.0, 0.0]])
    steps = [(good, [True, False])] * 3 + [(np.zeros((2, 3)), [False, False])] * 2
    wrapper = TemporalSmoothing(Scripted(steps))
    for _ in range(3):
        out = wrapper(observation(), info())
    assert np.allclose(out[0], good[0], atol=1e-6) and np.all(out[1] == 0)
    held = wrapper(observation(), info())
    assert np.allclose(held[0], good[0], atol=1e-6)  # inner kept the prior; estimate survives


def test_smoothing_reduces_noise_of_a_constant_correction():
    rng = np.random.default_rng(0)
    truth = np.array([0.6, 0.3, 0.004])
    noisy = truth + rng.normal(0.0, [0.05, 0.05, 0.001], size=(60, 3))
    steps = [(np.vstack([z, np.zeros(3)]), [True, False]) for z in noisy]
    wrapper = TemporalSmoothing(
        Scripted(steps), process_std=(0.005, 0.005, 1e-4), measurement_std=(0.05, 0.05, 0.001)
    )
    outputs = np.array([wrapper(observation(), info())[0] for _ in range(60)])
    raw_err = np.abs(noisy[20:, :2] - truth[:2]).mean()
    smooth_err = np.abs(outputs[20:, :2] - truth[:2]).mean()
    assert smooth_err < 0.5 * raw_err


def test_filters_follow_collaborator_ids_not_slots():
    a, b = np.array([1.0, 0.0, 0.0]), np.array([-1.0, 2.0, 0.0])
    steps = [(np.vstack([a, b]), [True, True]), (np.zeros((2, 3)), [False, False])]
    wrapper = TemporalSmoothing(Scripted(steps))
    wrapper(observation(), {"agent": "cav_0", "collaborators": ["cav_1", "rsu_0"]})
    swapped = wrapper(observation(), {"agent": "cav_0", "collaborators": ["rsu_0", "cav_1"]})
    assert np.allclose(swapped[0], b, atol=1e-6) and np.allclose(swapped[1], a, atol=1e-6)


def test_stale_estimates_expire_and_reset_forgets():
    steps = [(np.array([[1.0, 0, 0]]), [True])] + [(np.zeros((1, 3)), [False])] * 4
    inner = Scripted(steps)
    wrapper = TemporalSmoothing(inner, max_age=2)
    outs = [wrapper(observation(1, 1), info(1))[0, 0] for _ in range(4)]
    assert outs[:3] == pytest.approx([1.0, 1.0, 1.0], abs=1e-6) and outs[3] == 0.0
    wrapper.reset()
    assert inner.resets == 1
    assert wrapper(observation(1, 1), info(1))[0, 0] == 0.0


def test_yaw_is_filtered_across_the_wrap():
    steps = [
        (np.array([[0, 0, np.pi - 0.01]]), [True]),
        (np.array([[0, 0, -np.pi + 0.01]]), [True]),
    ]
    wrapper = TemporalSmoothing(Scripted(steps))
    wrapper(observation(1, 1), info(1))
    yaw = wrapper(observation(1, 1), info(1))[0, 2]
    assert abs(abs(yaw) - np.pi) < 0.02  # stays near +-pi, never averages to 0


def test_accepts_registry_names_and_validates():
    wrapper = TemporalSmoothing("identity")
    assert np.all(wrapper(observation(), info()) == 0)
    with pytest.raises(ValueError, match="process_std"):
        TemporalSmoothing("identity", process_std=(0.1, -1.0, 0.1))
    with pytest.raises(ValueError, match="policy_params"):
        TemporalSmoothing(Scripted([]), tau1=0.3)
    with pytest.raises(ValueError, match="unknown policy"):
        TemporalSmoothing("nope")


def test_wraps_a_real_aligner_on_a_static_scene():
    from roco_env.metrics import relative_pose_error
    from roco_env.policies.base import apply_correction
    from roco_env.policies.temporal import roco_temporal
    from roco_env.testing.constructed_scenes import (
        make_scene,
        pose_error,
        random_objects,
        to_observation,
    )

    objects = random_objects(np.random.default_rng(1), 12, 40.0)
    agents = np.array([[0.0, 0.0, 0.0], [15.0, 5.0, 0.5]])
    scene = make_scene(objects, agents, [pose_error(0.8, 0.8, 0.3)])
    obs = to_observation(scene, max_boxes=16, max_collaborators=2)
    wrapper = roco_temporal(max_age=5, tau2=2.5)
    for _ in range(3):
        action = wrapper(obs, {"agent": "cav_0", "collaborators": ["cav_1", None]})
    err = relative_pose_error(apply_correction(obs["collab_rel_poses"], action)[:1], scene.true)
    assert err[0, 0] < 0.1 and np.all(action[1] == 0)
    assert wrapper.last_result.applied.tolist() == [True, False]


def test_iid_corrections_are_followed_with_lag():
    """Documented limitation: when the true correction jumps every step (i.i.d. noise),
    the random-walk filter lags behind an exact inner policy."""
    rng = np.random.default_rng(1)
    truth = rng.normal(0.0, [0.8, 0.8, 0.01], size=(30, 3))
    steps = [(z[None], [True]) for z in truth]
    wrapper = TemporalSmoothing(Scripted(steps))
    outputs = np.array([wrapper(observation(1, 1), info(1))[0] for _ in range(30)])
    assert np.abs(outputs[1:, :2] - truth[1:, :2]).mean() > 0.1



class ReportsOnce(Scripted):
    """An inner policy that reports a result on its first call only (later calls return
    zeros and leave last_result as it was)."""

    def __call__(self, obs, info=None):
        if self.t == 0:
            return super().__call__(obs, info)
        return np.zeros((2, 3), np.float32)


def test_a_result_left_from_an_earlier_call_is_no_measurement():
    """Only the result of this very call says what was applied (roco_env.policies.base.act):
    a zero action from a call that reported nothing is a step without evidence, which
    inherits the estimate, though the inner policy's last_result still says applied."""
    good = np.array([[0.5, -0.2, 0.01], [0.0, 0.0, 0.0]])
    stale = ReportsOnce([(good, [True, False])])
    fresh = Scripted([(good, [True, False]), (np.zeros((2, 3)), [True, False])])
    held, measured = TemporalSmoothing(stale), TemporalSmoothing(fresh)
    held(observation(), info())
    measured(observation(), info())
    assert np.allclose(held(observation(), info())[0], good[0], atol=1e-6)
    assert stale.last_result.applied[0]  # left from the first call
    # the same zero action with this call's result saying applied is a measurement of zero
    assert np.linalg.norm(measured(observation(), info())[0]) < 0.6 * np.linalg.norm(good[0])
