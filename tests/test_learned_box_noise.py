"""The learned detector's box-precision knob: extra noise on the boxes agents report and
share, none on the feature maps intermediate fusion decodes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from roco_env.env import parallel_env
from roco_env.scenario import load_scenario
from roco_env.sensing import compute_visibility
from roco_env.sensing.learned import LearnedDetector, make_learned_detector
from roco_env.sensing.lidar import sample_scans
from roco_env.traffic import make_traffic_source

SIGMA = np.array([0.3, 0.3, 0.05])  # x, y (m), yaw (rad)
BLURRED = {"detector.params.box_sigma_xy": float(SIGMA[0]),
           "detector.params.box_sigma_yaw": float(SIGMA[2])}


@pytest.fixture(scope="module")
def crossing():
    """The V2XSet-shaped crossing: 3 CAVs and an RSU, about 18 vehicles around them."""
    state = make_traffic_source(load_scenario("v2xset_like")).reset(np.random.default_rng(3))
    return state, compute_visibility(state)


def test_box_noise_moves_each_box_by_its_sigma_widens_its_uncertainty_and_spares_the_maps(
        crossing):
    state, visibility = crossing
    plain = LearnedDetector()
    blurred = LearnedDetector(box_sigma_xy=float(SIGMA[0]), box_sigma_yaw=float(SIGMA[2]))
    before, maps_before = plain.perceive(state, visibility, np.random.default_rng(0))
    after, maps_after = blurred.perceive(state, visibility, np.random.default_rng(0))
    torch.testing.assert_close(maps_after.maps, maps_before.maps, rtol=0, atol=0)
    moves = []
    for was, now in zip(before, after, strict=True):
        np.testing.assert_array_equal(now.object_ids, was.object_ids)  # the same detections
        np.testing.assert_array_equal(now.scores, was.scores)
        np.testing.assert_array_equal(now.boxes[:, 2:6], was.boxes[:, 2:6])  # z and size kept
        np.testing.assert_allclose(now.uncertainty, np.hypot(was.uncertainty, SIGMA), rtol=1e-6)
        moves.append(now.boxes[:, [0, 1, 6]] - was.boxes[:, [0, 1, 6]])
    moves = np.concatenate(moves)
    assert len(moves) >= 40
    np.testing.assert_allclose(moves.mean(axis=0), 0.0, atol=3 * SIGMA.max() / np.sqrt(len(moves)))
    np.testing.assert_allclose(moves.std(axis=0), SIGMA, rtol=0.3)
    again, _ = blurred.perceive(state, visibility, np.random.default_rng(0))
    for first, second in zip(after, again, strict=True):  # the noise comes from the seed
        np.testing.assert_array_equal(first.boxes, second.boxes)


@pytest.mark.parametrize("key, value", [("box_sigma_xy", -0.1), ("box_sigma_xy", float("nan")),
                                        ("box_sigma_yaw", 4.0), ("box_sigma_yaw", "wide")])
def test_a_bad_box_sigma_is_a_clear_error(key, value):
    with pytest.raises(ValueError, match=f"detector.params.{key}"):
        make_learned_detector({key: value})


def test_perceive_draws_nothing_beyond_the_scans_with_or_without_box_noise(crossing):
    """Default episodes stay bit for bit as they were, and the box noise comes from a child
    stream: with or without it, perceive's only draws from its generator are the scans'."""
    state, visibility = crossing
    for detector in (LearnedDetector(), LearnedDetector(box_sigma_xy=float(SIGMA[0]))):
        perceived, scans_only = np.random.default_rng(0), np.random.default_rng(0)
        detector.perceive(state, visibility, perceived)
        sample_scans(state, visibility, detector.noise, scans_only)
        assert perceived.bit_generator.state == scans_only.bit_generator.state


def test_with_box_noise_uncorrected_intermediate_fusion_scores_as_without_it():
    """Every step's scans are those of the same seed without the knob, so what reads no
    shared box (intermediate fusion with the reported poses) is unchanged, step after step."""
    rewards = []
    for overrides in ({}, BLURRED):
        env = parallel_env("v2xset_like", detector="learned", fusion="intermediate",
                           max_cycles=4, **overrides)
        env.reset(seed=5)
        steps = []
        while env.agents:
            actions = {a: np.zeros(env.action_space(a).shape, np.float32) for a in env.agents}
            steps.append(env.step(actions)[1])
        rewards.append(steps)
    assert len(rewards[0]) == 4 and rewards[0] == rewards[1]


def _first_step(fusion: str, **overrides):
    """Reset observations, reset infos and first-step infos of a learned v2xset_like episode
    in which every agent keeps its reported poses."""
    env = parallel_env("v2xset_like", detector="learned", fusion=fusion, **overrides)
    observations, reset_infos = env.reset(seed=2)
    for agent, observation in observations.items():
        assert env.observation_space(agent).contains(observation), agent
    actions = {a: np.zeros(env.action_space(a).shape, dtype=np.float32) for a in env.agents}
    return observations, reset_infos, env.step(actions)[4]


def test_the_boxes_an_agent_shares_are_the_ones_it_reports_in_its_own_observation():
    observations, infos, _ = _first_step("intermediate", **BLURRED)
    default, _, _ = _first_step("intermediate")
    checked = 0
    for ego, observation in observations.items():
        for slot, sender in enumerate(infos[ego]["collaborators"]):
            own = observations[sender]
            count = int(own["box_mask"].sum())
            # One draw per box, sent as drawn: centres (each in the sender's frame) and
            # widened sigmas alike (headings differ only by the half-turn convention).
            np.testing.assert_array_equal(observation["collab_boxes"][slot, :count, :2],
                                          own["boxes"][:count, :2])
            np.testing.assert_array_equal(observation["collab_uncertainty"][slot, :count],
                                          own["uncertainty"][:count])
            checked += count
        assert not np.array_equal(observation["boxes"], default[ego]["boxes"])
    assert checked > 0


@pytest.mark.parametrize("fusion, boxes_change", [("intermediate", False), ("late", True),
                                                  ("none", True)])
def test_only_fusions_of_boxes_see_the_box_noise(fusion, boxes_change):
    """Intermediate fusion decodes the untouched maps (the step's scans are drawn first);
    late fusion merges the shared boxes and no fusion keeps the ego's own, both blurred."""
    _, _, plain = _first_step(fusion)
    _, _, blurred = _first_step(fusion, **BLURRED)
    same = [np.array_equal(plain[a]["fused_boxes"], blurred[a]["fused_boxes"])
            for a in plain if "fused_boxes" in plain[a]]
    assert len(same) == len(plain)  # every agent is an evaluated ego with fused boxes
    assert not any(same) if boxes_change else all(same)
