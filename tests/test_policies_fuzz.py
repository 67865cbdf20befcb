"""Degenerate inputs and hypothesis fuzzing of every array aligner and its policy."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from roco_env.policies import make_policy
from roco_env.policies.coalign import coalign_align
from roco_env.policies.fallback import roco_fallback_align
from roco_env.policies.freealign import freealign_align
from roco_env.policies.ransac import ransac_align
from roco_env.policies.roco import roco_align
from roco_env.policies.v2i_calib import v2i_calib_align
from roco_env.testing.constructed_scenes import (
    make_scene,
    pose_error,
    random_objects,
    to_observation,
)

ALIGNERS = [
    coalign_align,
    roco_align,
    ransac_align,
    v2i_calib_align,
    freealign_align,
    roco_fallback_align,
]
ALIGNER_POLICIES = ("coalign", "roco", "ransac", "v2i_calib", "freealign", "roco_fallback")
PAIR = np.array([[0.0, 0.0, 0.0], [10.0, -8.0, 0.7]])
REPORTED = np.array([[10.5, -7.5, 0.71]])


def car(x, y, yaw=0.0):
    return [x, y, 0.8, 4.5, 1.9, 1.6, yaw]


def check(result, reported):
    n = reported.shape[0]
    assert result.corrected.shape == (n, 3) and np.all(np.isfinite(result.corrected))
    assert result.applied.shape == (n,) and result.applied.dtype == bool
    assert np.array_equal(result.corrected[~result.applied], reported[~result.applied])
    assert np.all(np.isfinite(result.landmarks))
    assert result.matched_pairs.ndim == 2 and result.matched_pairs.shape[1] == 4


def unc(k, value=0.1):
    return np.full((k, 3), value)


def collinear():
    boxes = np.array([car(x, 0.0) for x in range(0, 50, 6)], dtype=float)
    return boxes, [boxes - [0.4, 0.2, 0, 0, 0, 0, 0]]


DEGENERATE = {
    "no boxes": (np.zeros((0, 7)), [np.zeros((0, 7))]),
    "one box": (np.array([car(5, 0)]), [np.array([car(-4, 7)])]),
    "no overlap": (np.array([car(5, 0), car(15, 3)]), [np.array([car(300, 0), car(320, 4)])]),
    "collinear": collinear(),
    "duplicates": (
        np.array([car(5, 0)] * 4 + [car(15, 2)] * 3, dtype=float),
        [np.array([car(5.3, 0.2)] * 5 + [car(15.2, 2.1)] * 2, dtype=float)],
    ),
}


@pytest.mark.parametrize("align", ALIGNERS)
@pytest.mark.parametrize("case", sorted(DEGENERATE))
def test_degenerate_inputs_keep_prior_or_stay_finite(align, case):
    ego, collab = DEGENERATE[case]
    result = align(ego, unc(len(ego)), collab, [unc(len(c)) for c in collab], REPORTED)
    check(result, REPORTED)
    if case in ("no boxes", "one box", "no overlap", "collinear"):
        assert not result.applied.any() and result.reason


@pytest.mark.parametrize("align", ALIGNERS)
@pytest.mark.parametrize("sigma", [np.nan, 0.0, np.inf])
def test_nan_zero_or_infinite_uncertainty(align, sigma):
    objects = random_objects(np.random.default_rng(0), 10, 30.0)
    scene = make_scene(objects, PAIR, [pose_error(0.8, 0.8, 1.0)])
    ego_unc = scene.ego_unc.copy()
    ego_unc[::2] = sigma
    result = align(scene.ego_boxes, ego_unc, scene.collab_boxes, scene.collab_unc, scene.reported)
    check(result, scene.reported)
    assert result.applied.all()


@pytest.mark.parametrize("align", ALIGNERS)
def test_boxes_flipped_by_pi(align):
    objects = random_objects(np.random.default_rng(1), 10, 30.0)
    scene = make_scene(objects, PAIR, [pose_error(0.8, 0.8, 1.0)])
    flipped = scene.collab_boxes[0].copy()
    flipped[::2, 6] = np.angle(np.exp(1j * (flipped[::2, 6] + np.pi)))
    result = align(scene.ego_boxes, scene.ego_unc, [flipped], scene.collab_unc, scene.reported)
    check(result, scene.reported)


@pytest.mark.parametrize("align", ALIGNERS)
def test_nan_boxes_are_rejected_with_a_clear_error(align):
    boxes = np.array([car(1, 1)], dtype=float)
    boxes[0, 0] = np.nan
    with pytest.raises(ValueError, match="ego boxes"):
        align(boxes, unc(1), [], [], np.zeros((0, 3)))


finite = st.floats(-60, 60, allow_nan=False)
sigma_st = st.one_of(st.floats(0, 2), st.just(np.nan), st.just(0.0))


@st.composite
def box_sets(draw, max_boxes=8):
    k = draw(st.integers(0, max_boxes))
    boxes = np.array(
        [
            [
                draw(finite),
                draw(finite),
                0.8,
                draw(st.floats(0, 6)),
                draw(st.floats(0, 3)),
                1.5,
                draw(st.floats(-4, 4)),
            ]
            for _ in range(k)
        ]
    ).reshape(k, 7)
    sig = np.array([[draw(sigma_st) for _ in range(3)] for _ in range(k)]).reshape(k, 3)
    return boxes, sig


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(ego=box_sets(), collabs=st.lists(box_sets(), max_size=3), data=st.data())
def test_fuzz_random_inputs(ego, collabs, data):
    reported = np.array(
        [[data.draw(finite), data.draw(finite), data.draw(st.floats(-3.2, 3.2))] for _ in collabs]
    ).reshape(-1, 3)
    for align in ALIGNERS:
        result = align(ego[0], ego[1], [c[0] for c in collabs], [c[1] for c in collabs], reported)
        check(result, reported)


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 10_000), filled=st.integers(0, 3), max_boxes=st.integers(1, 12))
def test_fuzz_policies_on_padded_observations(seed, filled, max_boxes):
    rng = np.random.default_rng(seed)
    objects = random_objects(rng, int(rng.integers(0, 15)), 30.0)
    agents = np.vstack([np.zeros(3), rng.uniform(-20, 20, size=(filled, 3))])
    errors = rng.normal(0.0, [0.8, 0.8, 0.02], size=(filled, 3))
    scene = make_scene(objects, agents, errors, noise=(0.1, 0.1, 0.05), rng=rng)
    obs = to_observation(scene, max_boxes=max_boxes, max_collaborators=3)
    for name in ALIGNER_POLICIES:
        policy = make_policy(name)
        action = policy(obs)
        assert action.shape == (3, 3) and action.dtype == np.float32
        assert np.all(np.isfinite(action)) and np.all(action[filled:] == 0)
        pairs = policy.last_result.matched_pairs
        assert np.all(pairs[:, [0, 2]] < filled) and np.all(pairs[:, [1, 3]] < max_boxes)
