"""Late fusion (merge + rotated NMS), the batched NMS, and intermediate feature fusion."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from roco_env.batched_nms import _iou_lower_bound, _separated, batched_nms_bev
from roco_env.fusion import (
    EGO_SOURCE,
    FusedDetections,
    late_fusion,
    merge_into_ego_frame,
    suppress,
)
from roco_env.fusion.intermediate import fuse_features
from roco_env.geometry import bev_iou, bev_iou_pairs, nms_bev, transform_boxes
from roco_env.sensing import BevGrid


def car(x, y, yaw=0.0, length=4.5, width=1.9):
    return np.array([x, y, 0.8, length, width, 1.6, yaw])


def random_scene(rng, n, spread):
    """n car-like boxes in a square of side ``spread`` m (crowded: many overlaps)."""
    return np.column_stack([
        rng.uniform(-spread / 2, spread / 2, (n, 2)), np.full(n, 0.8),
        rng.uniform(3.0, 6.0, n), rng.uniform(1.5, 2.5, n), np.full(n, 1.6),
        rng.uniform(-np.pi, np.pi, n)])


def test_collaborator_boxes_are_moved_with_the_relative_pose():
    pose = np.array([5.0, 2.0, np.pi / 2])
    fused = late_fusion(np.zeros((0, 7)), np.zeros(0), [car(10.0, 0.0)[None]], [np.array([0.9])],
                        pose[None])
    np.testing.assert_allclose(fused.boxes[0, [0, 1, 6]], [5.0, 12.0, np.pi / 2], atol=1e-12)
    assert fused.source.tolist() == [0] and fused.source_index.tolist() == [0]


def test_duplicates_merge_and_result_is_score_sorted():
    ego = np.stack([car(10.0, 0.0), car(30.0, 0.0)])
    # The collaborator sits 20 m ahead of the ego: its (0.2 m off) view of the ego's
    # first car is at its own x = -10; its second box is a car the ego does not see.
    collab = np.stack([car(-9.8, 0.0), car(0.0, 8.0)])
    fused = late_fusion(ego, np.array([0.6, 0.7]), [collab], [np.array([0.9, 0.5])],
                        np.array([[20.0, 0.0, 0.0]]))
    assert fused.scores.tolist() == [0.9, 0.7, 0.5]
    assert fused.source.tolist() == [0, EGO_SOURCE, 0]
    assert fused.source_index.tolist() == [0, 1, 1]
    np.testing.assert_allclose(fused.boxes[:, :2], [[10.2, 0.0], [30.0, 0.0], [20.0, 8.0]])


def test_merge_validates_its_inputs():
    with pytest.raises(ValueError, match="one entry per collaborator"):
        merge_into_ego_frame(np.zeros((0, 7)), np.zeros(0), [np.zeros((1, 7))], [],
                             np.zeros((1, 3)))
    with pytest.raises(ValueError, match=r"collab_boxes\[0\] contains NaN"):
        merge_into_ego_frame(np.zeros((0, 7)), np.zeros(0), [np.full((1, 7), np.nan)],
                             [np.ones(1)], np.zeros((1, 3)))
    with pytest.raises(ValueError, match="ego_scores must have one score per box"):
        merge_into_ego_frame(car(0, 0)[None], np.ones(2), [], [], np.zeros((0, 3)))
    two_slots = np.zeros((2, 3))
    with pytest.raises(ValueError, match=r"collab_boxes\[1\] must have shape"):
        merge_into_ego_frame(np.zeros((0, 7)), np.zeros(0), [car(0, 0)[None], np.zeros((1, 6))],
                             [np.ones(1), np.ones(1)], two_slots)
    with pytest.raises(ValueError, match=r"collab_boxes\[0\] has negative sizes"):
        merge_into_ego_frame(np.zeros((0, 7)), np.zeros(0), [car(0, 0, length=-1)[None], []],
                             [np.ones(1), []], two_slots)
    merged = merge_into_ego_frame(np.zeros((0, 7)), np.zeros(0), [[], car(1, 0)[None]],
                                  [[], np.ones(1)], two_slots)  # an empty 1-D slot is fine
    assert merged.source.tolist() == [1] and merged.source_index.tolist() == [0]


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), sizes=st.lists(st.integers(0, 60), min_size=1, max_size=4),
       threshold=st.sampled_from([0.0, 0.15, 0.5, 1.0]), ties=st.booleans())
def test_batched_nms_equals_geometry_nms(seed, sizes, threshold, ties):
    rng = np.random.default_rng(seed)
    boxes = [random_scene(rng, n, spread=30.0) for n in sizes]
    scores = [np.round(rng.random(n), 1) if ties else rng.random(n) for n in sizes]
    batched = batched_nms_bev(boxes, scores, threshold)
    for b, s, kept in zip(boxes, scores, batched, strict=True):
        np.testing.assert_array_equal(kept, nms_bev(b, s, threshold))


def duplicated_scene(rng, n_objects, copies, jitter):
    """Objects each detected ``copies`` times with centre/yaw noise (late fusion's input)."""
    base = random_scene(rng, n_objects, spread=40.0)
    boxes = np.repeat(base, copies, axis=0)
    boxes[:, :2] += rng.normal(0.0, jitter, (len(boxes), 2))
    boxes[:, 3:5] *= np.exp(rng.normal(0.0, 0.05, (len(boxes), 2)))
    boxes[:, 6] += rng.normal(0.0, rng.choice([0.02, 0.3]), len(boxes))
    return boxes


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), jitter=st.sampled_from([0.0, 0.1, 0.5, 1.5]),
       threshold=st.sampled_from([0.0, 0.15, 0.5, 0.9]))
def test_nms_shortcuts_change_no_decision(seed, jitter, threshold):
    """The IoU lower bound and the separating-axis test only skip exact IoUs."""
    rng = np.random.default_rng(seed)
    boxes = [duplicated_scene(rng, int(rng.integers(1, 25)), 4, jitter) for _ in range(2)]
    scores = [np.round(rng.random(len(b)), 1) for b in boxes]
    for b, s, kept in zip(boxes, scores, batched_nms_bev(boxes, scores, threshold), strict=True):
        np.testing.assert_array_equal(kept, nms_bev(b, s, threshold))
    first, second = np.triu_indices(len(boxes[0]), 1)
    a, b = boxes[0][first], boxes[0][second]
    exact = bev_iou_pairs(a, b)
    bound = _iou_lower_bound(a, b)
    assert np.all(bound <= exact + 1e-12)
    assert np.all(exact[_separated(a, b)] == 0.0)


def test_iou_lower_bound_decides_most_duplicates():
    rng = np.random.default_rng(5)
    base = random_scene(rng, 200, spread=400.0)
    copy = base.copy()
    copy[:, :2] += rng.normal(0.0, 0.2, (200, 2))
    copy[:, 6] += rng.normal(0.0, 0.05, 200)
    exact, bound = bev_iou_pairs(base, copy), _iou_lower_bound(base, copy)
    assert np.all(bound <= exact + 1e-12) and np.all(bound >= 0.0)
    assert np.mean(bound > 0.15) > 0.9  # no exact IoU needed for these at the NMS threshold
    np.testing.assert_allclose(_iou_lower_bound(base, base), 1.0, atol=1e-12)


def test_suppress_matches_single_ego_late_fusion():
    rng = np.random.default_rng(0)
    egos = [(random_scene(rng, 20, 40.0), rng.random(20), [random_scene(rng, 15, 40.0)],
             [rng.random(15)], rng.normal(0.0, 1.0, (1, 3))) for _ in range(3)]
    merged = [merge_into_ego_frame(*ego) for ego in egos]
    for together, ego in zip(suppress(merged), egos, strict=True):
        alone = late_fusion(*ego)
        np.testing.assert_array_equal(together.boxes, alone.boxes)
        np.testing.assert_array_equal(together.source, alone.source)


def test_batched_nms_validates_inputs():
    with pytest.raises(ValueError, match="same number of sets"):
        batched_nms_bev([np.zeros((0, 7))], [], 0.1)
    with pytest.raises(ValueError, match=r"scores\[0\] must hold one finite score"):
        batched_nms_bev([car(0, 0)[None]], [np.array([np.nan])], 0.1)
    with pytest.raises(ValueError, match="iou_threshold must be in"):
        batched_nms_bev([], [], 1.5)
    assert batched_nms_bev([np.zeros((0, 7)), car(0, 0)[None]], [np.zeros(0), np.ones(1)],
                           0.15)[1].tolist() == [0]


def test_boxes_on_the_ego_footprint_are_dropped():
    footprint = car(0.0, 0.0)
    # The collaborator, 20 m ahead, sees the ego's car 1 m to the side of where it is
    # (pose error): centre outside the footprint, IoU 0.31 > 0.15. Its second box is the
    # car queued 6 m ahead of the ego, which the ego sees too.
    args = (car(6.0, 0.0)[None], np.array([0.6]), [np.stack([car(-20.0, 1.0), car(-14.1, 0.1)])],
            [np.array([0.95, 0.5])], np.array([[20.0, 0.0, 0.0]]))
    fused = late_fusion(*args, ego_footprint=footprint)
    assert fused.source.tolist() == [EGO_SOURCE] and fused.scores.tolist() == [0.6]
    # Without a footprint (an RSU ego) the view of the ego's car stays: a false positive.
    for kept in (late_fusion(*args), late_fusion(*args, ego_footprint=None)):
        assert kept.source.tolist() == [0, EGO_SOURCE] and kept.scores.tolist() == [0.95, 0.6]
        assert bev_iou(kept.boxes[:1], footprint[None])[0, 0] == pytest.approx(4.05 / 13.05)
    # A dropped box suppresses nothing: B (IoU 0.46 with A, 0.086 with the footprint)
    # survives although A (IoU 0.36 with the footprint) has the higher score.
    beside = late_fusion(np.zeros((0, 7)), np.zeros(0), [np.stack([car(0.0, 0.9), car(0.0, 1.6)])],
                         [np.array([0.9, 0.8])], np.zeros((1, 3)), ego_footprint=footprint)
    assert beside.source_index.tolist() == [1]


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), sizes=st.lists(st.integers(0, 40), min_size=1, max_size=4),
       threshold=st.sampled_from([0.0, 0.15, 0.5]))
def test_footprint_equals_dropping_its_overlaps_before_nms(seed, sizes, threshold):
    rng = np.random.default_rng(seed)
    merged = [merge_into_ego_frame(random_scene(rng, n, 20.0), np.round(rng.random(n), 1), [],
                                   [], np.zeros((0, 3))) for n in sizes]
    footprints = [None if rng.random() < 0.3 else random_scene(rng, 1, 10.0)[0] for _ in sizes]
    for m, footprint, fused in zip(merged, footprints, suppress(merged, threshold, footprints),
                                   strict=True):
        keep = (np.arange(len(m)) if footprint is None else
                np.flatnonzero(bev_iou(m.boxes, footprint[None])[:, 0] <= threshold))
        expected = keep[nms_bev(m.boxes[keep], m.scores[keep], threshold)]
        np.testing.assert_array_equal(fused.source_index, expected)


def test_footprints_are_validated():
    merged = [merge_into_ego_frame(car(0, 0)[None], np.ones(1), [], [], np.zeros((0, 3)))]
    with pytest.raises(ValueError, match="footprints must hold one entry"):
        suppress(merged, 0.15, [None, None])
    with pytest.raises(ValueError, match=r"footprints\[0\] must be one box"):
        suppress(merged, 0.15, [np.zeros((2, 7))])
    with pytest.raises(ValueError, match=r"footprints\[0\] contains NaN"):
        suppress(merged, 0.15, [np.full(7, np.nan)])
    bad = FusedDetections(np.zeros((1, 7)), np.array([np.nan]), np.zeros(1, np.int64),
                          np.zeros(1, np.int64))
    with pytest.raises(ValueError, match=r"merged\[0\]\.scores must hold one finite score"):
        suppress([bad])
    with pytest.raises(ValueError, match=r"merged boxes\[1\] has negative sizes"):
        suppress([merged[0], FusedDetections(-np.ones((1, 7)), np.ones(1), np.zeros(1, np.int64),
                                             np.zeros(1, np.int64))])
    with pytest.raises(ValueError, match="ego_footprint must be one box"):
        late_fusion(np.zeros((0, 7)), np.zeros(0), [], [], np.zeros((0, 3)),
                    ego_footprint=np.zeros(6))


GRID = BevGrid((-20.0, 20.0), (-10.0, 10.0), 0.4)


def test_feature_fusion_warps_with_the_relative_pose_and_takes_the_max():
    ego = torch.zeros(2, GRID.H, GRID.W)
    ego[0, 10, 10] = 0.5
    collab = torch.zeros(2, GRID.H, GRID.W)
    row, col = GRID.cell_index(np.array([1.0]), np.array([-2.0]))
    collab[1, row[0], col[0]] = 2.0
    shift = np.array([[4.0, 2.0, 0.0]])  # collaborator frame -> ego frame: +4 m x, +2 m y
    fused = fuse_features(ego, [collab], shift, GRID)
    moved_row, moved_col = GRID.cell_index(np.array([5.0]), np.array([0.0]))
    assert fused[1].argmax().item() == moved_row[0] * GRID.W + moved_col[0]
    assert fused[1].max().item() == pytest.approx(2.0, rel=1e-4)  # float32 bilinear weights
    assert fused[0, 10, 10].item() == 0.5 and torch.all(fused >= ego)


def test_feature_fusion_edge_cases():
    ego = torch.rand(3, GRID.H, GRID.W)
    alone = fuse_features(ego, [], np.zeros((0, 3)), GRID)
    assert torch.equal(alone, ego) and alone is not ego
    with pytest.raises(ValueError, match="one pose per collaborator map"):
        fuse_features(ego, [ego], np.zeros((2, 3)), GRID)


def test_transform_consistency_of_fused_boxes():
    """Fusing with T and then moving by U equals fusing with U*T (frames compose)."""
    rng = np.random.default_rng(1)
    collab = random_scene(rng, 8, 40.0)
    t = np.array([3.0, -1.0, 0.3])
    fused = late_fusion(np.zeros((0, 7)), np.zeros(0), [collab], [np.linspace(1, 0.1, 8)], t[None])
    direct = transform_boxes(collab, t)
    assert all(any(np.allclose(f, d) for d in direct) for f in fused.boxes)
