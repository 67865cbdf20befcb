"""Late fusion (merge + rotated NMS), the batched NMS, and intermediate feature fusion."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from roco_env.fusion import EGO_SOURCE, late_fusion, merge_into_ego_frame, suppress
from roco_env.fusion.intermediate import fuse_features
from roco_env.fusion.nms import batched_nms_bev
from roco_env.geometry import nms_bev, transform_boxes
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
