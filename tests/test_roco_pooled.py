"""RoCo's pooled significance: the do-no-harm test decided over a collaborator's frames."""

import numpy as np
import pytest
from test_roco import calibrated_scene, errors

import roco_env
from roco_env.policies import make_policy
from roco_env.policies.pooled import PooledSignificance
from roco_env.policies.roco import NOT_SIGNIFICANT, roco_align
from roco_env.testing.constructed_scenes import pose_error, to_observation

LEVEL = 0.9999


def test_the_pooled_test_waives_on_evidence_and_rarely_under_its_null():
    pooled = PooledSignificance(LEVEL, window=20, min_frames=3)
    for _ in range(3):  # clearly wrong poses: waived once three frames are recorded
        assert not pooled.waived("wrong")
        pooled.record(["wrong", "untested"], [40.0, np.nan])
    assert pooled.waived("wrong") and not pooled.waived("untested")
    rng = np.random.default_rng(0)
    false_alarms = 0
    for statistic in rng.chisquare(3, 2000):  # right poses: the statistic's null
        false_alarms += pooled.waived("right")
        pooled.record(["right"], [statistic])
    assert false_alarms <= 10  # 0.5% of the frames at most (level 1e-4 per frame)
    pooled.reset()
    assert not pooled.waived("wrong")
    for bad in ({"level": 1.0}, {"level": 0.0}, {"level": 0.9, "min_frames": 0},
                {"level": 0.9, "window": 2, "min_frames": 3}):
        with pytest.raises(ValueError):
            PooledSignificance(**bad)


def test_a_waived_test_applies_what_one_frame_cannot_show():
    """Errors of 0.15 m / 0.15 deg: most frames alone keep the reported pose; with the test
    waived the correction is applied, with the same statistic, and the errors shrink."""
    before, after = [], []
    for seed in range(20):
        scene = calibrated_scene(seed, pose_error(0.15, 0.15, 1.0))
        kept = roco_align(*scene.args())
        if kept.applied[0]:
            continue
        assert kept.slot_reasons[0].startswith(NOT_SIGNIFICANT)
        waived = roco_align(*scene.args(), waived=[0])
        assert waived.applied[0] and waived.slot_reasons == ("",)
        assert waived.slot_statistics == kept.slot_statistics
        assert np.isfinite(kept.slot_statistics[0])
        before.append(errors(kept, scene)[0][0])
        after.append(errors(waived, scene)[0][0])
    assert len(before) >= 8
    assert np.mean(after) < 0.6 * np.mean(before)
    scene = calibrated_scene(0, np.zeros(3))
    with pytest.raises(ValueError, match="waived"):
        roco_align(*scene.args(), waived=[1])
    assert np.isnan(roco_align(*scene.args(), significance=None).slot_statistics[0])


def _episode(noise: float, policy_params: dict, steps: int = 12):
    """Per step, every agent's action and its slots' reasons, on v2xset_like (3 CAVs +
    1 RSU, realistic detector) with pose noise ``noise`` (m / deg) on every agent."""
    env = roco_env.parallel_env("v2xset_like", max_cycles=steps, sigma_t=noise, sigma_r=noise,
                                **{"noise.perturb_ego": True})
    observations, infos = env.reset(seed=1)
    policy = make_policy("roco", **policy_params)  # one instance serves every agent
    frames = []
    while env.agents:
        actions, reasons = {}, []
        for agent in env.agents:
            actions[agent] = policy(observations[agent], infos[agent])
            filled = np.nonzero(observations[agent]["collab_mask"] > 0)[0]
            reasons += [policy.last_result.slot_reasons[s] for s in filled]
        frames.append((actions, reasons))
        observations, _, _, _, infos = env.step(actions)
    return frames


def test_the_policy_corrects_small_errors_and_leaves_clean_poses_alone():
    pooled = {"pooled_significance": LEVEL}
    kept = [sum(r.startswith(NOT_SIGNIFICANT) for _, reasons in _episode(0.2, params)[4:]
                for r in reasons) for params in ({}, pooled)]
    assert kept[0] >= 3 and kept[1] == 0  # after the first frames, none kept
    for (plain, _), (with_pool, _) in zip(_episode(0.0, {}), _episode(0.0, pooled),
                                          strict=True):
        for agent in plain:  # clean poses: the pooled test never waives
            np.testing.assert_array_equal(plain[agent], with_pool[agent])


def test_pooled_significance_is_checked_and_stateful_only_when_on():
    assert not make_policy("roco").keeps_state
    policy = make_policy("roco", pooled_significance=LEVEL)
    assert "collaborator" in policy.keeps_state
    for bad in ({"pooled_significance": 1.5}, {"pooled_significance": 0},
                {"pooled_significance": LEVEL, "significance": None}):
        with pytest.raises(ValueError, match="significance"):
            make_policy("roco", **bad)


def _gapped_observation(error):
    """A calibrated scene's one collaborator in the last of three slots (the first two empty)."""
    scene = calibrated_scene(3, error)
    observation = to_observation(scene, max_boxes=20, max_collaborators=3)
    for key in [k for k in observation if k.startswith("collab_")]:
        observation[key] = np.roll(observation[key], 2, axis=0)
    return observation


def test_statistics_reach_the_observation_slots_and_reset_forgets_the_history():
    policy = make_policy("roco", pooled_significance=LEVEL)
    info = {"agent": "cav_0", "collaborators": ["rsu_0", "cav_1", "cav_2"]}
    observation = _gapped_observation(pose_error(0.3, 0.3, 1.0))
    for _ in range(3):
        policy(observation, info)
    statistics = policy.last_result.slot_statistics
    assert np.isnan(statistics[0]) and np.isnan(statistics[1]) and statistics[2] > 11.35
    assert policy.pooled.waived(("cav_0", "cav_2"))
    policy.reset()
    assert not policy.pooled.waived(("cav_0", "cav_2"))
