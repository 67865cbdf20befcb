"""SE(2) algebra, box transforms, exact BEV IoU and rotated NMS (roco_env.geometry)."""

from __future__ import annotations

import numpy as np
import pytest
import shapely
from hypothesis import given, settings
from hypothesis import strategies as st

from roco_env.geometry import (
    AXIAL_HEADING_LOW,
    bev_candidate_pairs,
    bev_iou,
    bev_iou_pairs,
    box_corners_bev,
    canonical_axial_yaw,
    matrix_to_se2,
    nms_bev,
    se2_apply,
    se2_compose,
    se2_inverse,
    se2_relative,
    se2_to_matrix,
    transform_boxes,
    validate_boxes,
    wrap_angle,
)


def shapely_iou_pairs(boxes_a: np.ndarray, boxes_b: np.ndarray) -> np.ndarray:
    """Oracle: IoU of aligned pairs with shapely polygons (exact up to rounding)."""
    poly_a = shapely.polygons(box_corners_bev(boxes_a))
    poly_b = shapely.polygons(box_corners_bev(boxes_b))
    inter = shapely.area(shapely.intersection(poly_a, poly_b))
    union = shapely.area(poly_a) + shapely.area(poly_b) - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)


def random_boxes(rng: np.random.Generator, n: int, spread: float = 3.0,
                 centre: float = 0.0) -> np.ndarray:
    boxes = np.empty((n, 7))
    boxes[:, :2] = centre + rng.uniform(-spread, spread, (n, 2))
    boxes[:, 2] = rng.uniform(-1, 1, n)
    boxes[:, 3:6] = rng.uniform(0.5, 6.0, (n, 3))
    boxes[:, 6] = rng.uniform(-np.pi, np.pi, n)
    return boxes


def pair_cases(rng: np.random.Generator) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """>= 10,000 aligned pairs covering general, touching, nested, identical, flipped, thin."""
    n = 2000
    general_a, general_b = random_boxes(rng, n), random_boxes(rng, n)
    far_a, far_b = random_boxes(rng, n, centre=150.0), random_boxes(rng, n, centre=150.0)
    # Touching: b is a's neighbour sharing a full or partial side (same yaw).
    touch_a = random_boxes(rng, n)
    touch_b = touch_a.copy()
    shift = np.where(rng.random(n) < 0.5, 0.5 * (touch_a[:, 3] + touch_b[:, 3]), 0.0)
    side = np.where(shift == 0.0, 0.5 * (touch_a[:, 4] + touch_b[:, 4]), 0.0)
    slide = rng.uniform(-1.0, 1.0, n) * (shift == 0.0)
    c, s = np.cos(touch_a[:, 6]), np.sin(touch_a[:, 6])
    touch_b[:, 0] += c * (shift + slide) - s * side
    touch_b[:, 1] += s * (shift + slide) + c * side
    # Corner touching (different yaw) and axis-aligned exact contact.
    aligned_a = random_boxes(rng, 500)
    aligned_a[:, 6] = 0.0
    aligned_b = aligned_a.copy()
    aligned_b[:, 0] += aligned_a[:, 3]
    # Nested: b strictly inside a, arbitrary yaw.
    nest_a = random_boxes(rng, n)
    nest_a[:, 3:5] += 4.0
    nest_b = nest_a.copy()
    nest_b[:, 3:5] = rng.uniform(0.2, 1.0, (n, 2))
    nest_b[:, :2] += rng.uniform(-1.0, 1.0, (n, 2))
    nest_b[:, 6] = rng.uniform(-np.pi, np.pi, n)
    same = random_boxes(rng, 1000)
    flipped = same.copy()
    flipped[:, 6] = wrap_angle(flipped[:, 6] + np.pi)
    thin_a = random_boxes(rng, 1000)
    thin_a[:, 4] = rng.choice([0.0, 1e-9, 1e-6, 1e-3], 1000)
    thin_b = random_boxes(rng, 1000, spread=1.0)
    thin_b[500:, 3] = 1e-6
    # Nearly coincident edges: tiny rotations and shifts, far from the origin too.
    near_a = random_boxes(rng, n)
    near_a[:, :2] += rng.choice([0.0, 1e3, -3e4], n)[:, None]
    near_b = near_a.copy()
    near_b[:, 6] += rng.choice([0.0, 1e-15, 1e-12, 1e-9, 1e-6, 1e-3], n) * rng.choice([-1, 1], n)
    near_b[:, :2] += rng.choice([0.0, 1e-14, 1e-11, 1e-8, 1e-5], (n, 2)) * rng.choice([-1, 1], (n, 2))
    near_b[::3, 3] *= 0.5
    flip = rng.random(n) < 0.3
    near_b[flip, 6] = wrap_angle(near_b[flip, 6] + np.pi)
    return {
        "general": (general_a, general_b),
        "nearly coincident edges": (near_a, near_b),
        "far from origin": (far_a, far_b),
        "touching side": (touch_a, touch_b),
        "touching axis aligned": (aligned_a, aligned_b),
        "nested": (nest_a, nest_b),
        "identical": (same, same.copy()),
        "rotated by pi": (same, flipped),
        "degenerate thin": (thin_a, thin_b),
    }


def test_iou_matches_shapely_on_10k_pairs():
    cases = pair_cases(np.random.default_rng(2024))
    total = 0
    for name, (a, b) in cases.items():
        ours, oracle = bev_iou_pairs(a, b), shapely_iou_pairs(a, b)
        total += len(a)
        assert np.max(np.abs(ours - oracle)) < 1e-9, name
        dense = bev_iou(a[:100], b[:100])
        np.testing.assert_allclose(np.diag(dense), oracle[:100], rtol=0, atol=1e-9, err_msg=name)
    assert total >= 10_000
    np.testing.assert_allclose(bev_iou_pairs(*cases["identical"]), 1.0, atol=1e-12)
    np.testing.assert_allclose(bev_iou_pairs(*cases["rotated by pi"]), 1.0, atol=1e-12)
    nested_a, nested_b = cases["nested"]
    area_ratio = nested_b[:, 3] * nested_b[:, 4] / (nested_a[:, 3] * nested_a[:, 4])
    np.testing.assert_allclose(bev_iou_pairs(nested_a, nested_b), area_ratio, atol=1e-12)
    assert np.all(bev_iou_pairs(*cases["touching axis aligned"]) < 1e-12)


def test_dense_iou_matches_shapely_matrix():
    rng = np.random.default_rng(5)
    a, b = random_boxes(rng, 60, spread=8.0), random_boxes(rng, 45, spread=8.0)
    ia, ib = np.meshgrid(np.arange(60), np.arange(45), indexing="ij")
    oracle = shapely_iou_pairs(a[ia.ravel()], b[ib.ravel()]).reshape(60, 45)
    dense = bev_iou(a, b)
    assert dense.shape == (60, 45)
    assert np.max(np.abs(dense - oracle)) < 1e-9
    assert 0 < np.count_nonzero(dense) < dense.size
    assert bev_iou(a, np.zeros((0, 7))).shape == (60, 0)


def test_candidate_pairs_cover_overlaps_and_respect_groups():
    rng = np.random.default_rng(8)
    a, b = random_boxes(rng, 80, spread=15.0), random_boxes(rng, 70, spread=15.0)
    ia, ib = bev_candidate_pairs(a, b)
    iou = bev_iou(a, b)
    candidate = np.zeros(iou.shape, dtype=bool)
    candidate[ia, ib] = True
    assert np.all(candidate[iou > 0]) and candidate.sum() < candidate.size
    groups_a, groups_b = np.sort(rng.integers(0, 5, 80)), np.sort(rng.integers(0, 5, 70))
    ga, gb = bev_candidate_pairs(a, b, groups_a, groups_b)
    same = groups_a[:, None] == groups_b[None, :]
    expected_a, expected_b = np.nonzero(candidate & same)
    np.testing.assert_array_equal(ga, expected_a)
    np.testing.assert_array_equal(gb, expected_b)
    with pytest.raises(ValueError, match="groups_a"):
        bev_candidate_pairs(a, b, groups_a[::-1], groups_b)
    with pytest.raises(ValueError, match="together"):
        bev_candidate_pairs(a, b, groups_a, None)


box_strategy = st.tuples(
    st.floats(-20, 20), st.floats(-20, 20), st.floats(-2, 2),
    st.floats(0.05, 8), st.floats(0.05, 8), st.floats(0.1, 4), st.floats(-np.pi, np.pi),
).map(lambda t: np.array(t, dtype=float))
pose_strategy = st.tuples(st.floats(-500, 500), st.floats(-500, 500), st.floats(-np.pi, np.pi))


@settings(max_examples=150, deadline=None)
@given(box_strategy, box_strategy, pose_strategy)
def test_iou_properties(a, b, pose):
    ab = bev_iou(a[None], b[None])[0, 0]
    assert 0.0 <= ab <= 1.0
    assert bev_iou(b[None], a[None])[0, 0] == pytest.approx(ab, abs=1e-12)
    assert bev_iou(a[None], a[None])[0, 0] == pytest.approx(1.0, abs=1e-12)
    moved = bev_iou(transform_boxes(a[None], pose), transform_boxes(b[None], pose))[0, 0]
    assert moved == pytest.approx(ab, abs=1e-9)


# ---------------------------------------------------------------- SE(2)


@settings(max_examples=100, deadline=None)
@given(pose_strategy, pose_strategy)
def test_se2_round_trips(a, b):
    a, b = np.array(a), np.array(b)
    identity = se2_compose(a, se2_inverse(a))
    np.testing.assert_allclose(identity, 0.0, atol=1e-9)
    round_trip = matrix_to_se2(se2_to_matrix(a))
    np.testing.assert_allclose(round_trip[:2], a[:2], atol=1e-12)
    assert abs(wrap_angle(round_trip[2] - a[2])) < 1e-12
    assert -np.pi < round_trip[2] <= np.pi
    np.testing.assert_allclose(
        se2_to_matrix(se2_compose(a, b)), se2_to_matrix(a) @ se2_to_matrix(b), atol=1e-9
    )
    relative = se2_relative(a, b)
    np.testing.assert_allclose(se2_to_matrix(se2_compose(a, relative)), se2_to_matrix(b),
                               atol=1e-9)
    point = np.array([3.0, -2.0])
    homogeneous = se2_to_matrix(a) @ np.array([*point, 1.0])
    np.testing.assert_allclose(se2_apply(a, point), homogeneous[:2], atol=1e-9)


def test_wrap_angle_interval():
    angles = np.array([np.pi, -np.pi, 3 * np.pi, -3 * np.pi, 0.0, 7.0, -7.0])
    wrapped = wrap_angle(angles)
    assert np.all((wrapped > -np.pi) & (wrapped <= np.pi))
    np.testing.assert_allclose(wrapped[:4], np.pi)
    np.testing.assert_allclose(np.cos(wrapped), np.cos(angles), atol=1e-12)


def test_batched_se2_broadcasts():
    rng = np.random.default_rng(0)
    poses = rng.uniform(-3, 3, (5, 4, 3))
    composed = se2_compose(poses, se2_inverse(poses))
    assert composed.shape == (5, 4, 3)
    np.testing.assert_allclose(composed, 0.0, atol=1e-12)


def test_transform_boxes_moves_corners_rigidly():
    rng = np.random.default_rng(1)
    boxes = random_boxes(rng, 20, spread=30.0)
    pose = np.array([12.0, -4.0, 2.5])
    moved = transform_boxes(boxes, pose)
    np.testing.assert_allclose(box_corners_bev(moved), se2_apply(pose, box_corners_bev(boxes)),
                               atol=1e-9)
    np.testing.assert_array_equal(moved[:, 2:6], boxes[:, 2:6])
    assert np.all((moved[:, 6] > -np.pi) & (moved[:, 6] <= np.pi))
    back = transform_boxes(moved, se2_inverse(pose))
    np.testing.assert_allclose(back[:, :6], boxes[:, :6], atol=1e-9)
    np.testing.assert_allclose(wrap_angle(back[:, 6] - boxes[:, 6]), 0.0, atol=1e-12)


def test_corners_are_counter_clockwise():
    corners = box_corners_bev(np.array([[1.0, 2.0, 0.0, 4.0, 2.0, 1.5, 0.0]]))[0]
    np.testing.assert_allclose(corners, [[3, 3], [-1, 3], [-1, 1], [3, 1]])
    x, y = corners[:, 0], corners[:, 1]
    assert 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) == pytest.approx(8.0)


# ---------------------------------------------------------------- NMS


def reference_nms(boxes: np.ndarray, scores: np.ndarray, thr: float) -> list[int]:
    """Plain loop: keep the best remaining box, drop those overlapping it by more than thr."""
    order = sorted(range(len(scores)), key=lambda i: -scores[i])
    kept: list[int] = []
    for i in order:
        if all(shapely_iou_pairs(boxes[[i]], boxes[[k]])[0] <= thr for k in kept):
            kept.append(i)
    return kept


@pytest.mark.parametrize("seed", range(6))
def test_nms_matches_reference_loop(seed):
    rng = np.random.default_rng(seed)
    boxes = random_boxes(rng, 60, spread=10.0)
    scores = np.round(rng.random(60), 1)  # ties resolved by input order
    for thr in (0.0, 0.1, 0.3, 0.7):
        np.testing.assert_array_equal(nms_bev(boxes, scores, thr), reference_nms(boxes, scores, thr))
    assert nms_bev(np.zeros((0, 7)), [], 0.5).shape == (0,)


# ---------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: validate_boxes(np.zeros((3, 6)), "pred"), "pred must have shape"),
        (lambda: validate_boxes([[0, 0, 0, 1, 1, 1, np.nan]]), "boxes contains NaN"),
        (lambda: bev_iou([[0, 0, 0, 1, 1, 1, np.inf]], np.zeros((1, 7))), "boxes_a"),
        (lambda: bev_iou(np.zeros((1, 7)), [[0, 0, 0, -1, 1, 1, 0]]), "boxes_b.*negative"),
        (lambda: bev_iou_pairs(np.zeros((2, 7)), np.zeros((3, 7))), "same shape"),
        (lambda: nms_bev(np.zeros((2, 7)), [1.0], 0.5), "scores"),
        (lambda: nms_bev(np.zeros((1, 7)), [np.nan], 0.5), "scores"),
        (lambda: nms_bev(np.zeros((1, 7)), [1.0], 1.5), "iou_threshold"),
        (lambda: se2_compose(np.zeros(2), np.zeros(3)), "a must have shape"),
        (lambda: matrix_to_se2(np.zeros((2, 2))), "mats"),
        (lambda: transform_boxes(np.zeros((1, 7)), np.zeros(4)), "pose"),
    ],
)
def test_bad_input_raises_value_error(call, match):
    with pytest.raises(ValueError, match=match):
        call()


angles = st.floats(-10.0, 10.0, allow_nan=False)


@given(yaw=angles, frame_yaw=angles)
def test_canonical_axial_yaw_moves_a_heading_by_whole_half_turns_into_the_convention(
        yaw, frame_yaw):
    out = float(canonical_axial_yaw(np.array([yaw]), frame_yaw)[0])
    half_turns = (out - yaw) / np.pi
    assert abs(half_turns - round(half_turns)) < 1e-9
    seen = np.mod(out + frame_yaw - AXIAL_HEADING_LOW, 2.0 * np.pi)
    assert seen < np.pi + 1e-9 or seen > 2.0 * np.pi - 1e-9
    assert -np.pi < out <= np.pi


@given(heading=angles, frame_a=angles, frame_b=angles, flip_a=st.booleans(),
       flip_b=st.booleans())
def test_two_frames_that_know_their_relative_yaw_agree_on_an_axial_heading(
        heading, frame_a, frame_b, flip_a, flip_b):
    """An object's heading seen by agent a (frame yaw frame_a) and by agent b, each
    possibly flipped by pi, lands on the same world heading once canonicalised
    in a's frame (b's boxes via the relative yaw b -> a)."""
    in_a = heading - frame_a + (np.pi if flip_a else 0.0)
    in_b = heading - frame_b + (np.pi if flip_b else 0.0)
    mine = canonical_axial_yaw(np.array([in_a]), 0.0)[0]
    theirs = canonical_axial_yaw(np.array([in_b]), frame_b - frame_a)[0] + frame_b - frame_a
    gap = np.mod(mine - theirs + np.pi, 2.0 * np.pi) - np.pi
    # Equal, unless the heading sits on the edge of the half-turn (then pi apart).
    edge = np.mod(mine - AXIAL_HEADING_LOW + 1e-7, np.pi) < 2e-7
    assert abs(gap) < 1e-7 or (edge and abs(abs(gap) - np.pi) < 1e-7)
