"""The learned detector's box-precision knob: extra noise on the boxes agents report and
share, none on the feature maps intermediate fusion decodes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from roco_env.scenario import load_scenario
from roco_env.sensing import compute_visibility
from roco_env.sensing.learned import LearnedDetector, make_learned_detector
from roco_env.traffic import make_traffic_source

SIGMA = np.array([0.3, 0.3, 0.05])  # x, y (m), yaw (rad)


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
