"""AP protocol, evaluation range, relative pose error and success rate (roco_env.metrics)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import shapely
from hypothesis import given, settings
from hypothesis import strategies as st

from roco_env import metrics
from roco_env.geometry import box_corners_bev
from roco_env.metrics import (
    APAccumulator,
    FrameStats,
    frame_ap,
    frame_stats,
    in_range_mask,
    match_frames,
    relative_pose_error,
    success_rate,
)

THRESHOLDS = (0.3, 0.5, 0.7)


def car(x: float, y: float = 0.0, yaw: float = 0.0, length: float = 4.0,
        width: float = 2.0) -> list[float]:
    return [x, y, 0.0, length, width, 1.5, yaw]


def voc_ap_from_steps(recall: list[float], precision: list[float]) -> float:
    """VOC all-point AP from written (recall, precision) steps, as OpenCOOD's voc_ap loops."""
    mrec = [0.0, *recall, 1.0]
    mpre = [0.0, *precision, 0.0]
    for i in range(len(mpre) - 2, -1, -1):
        mpre[i] = max(mpre[i], mpre[i + 1])
    return sum((mrec[i] - mrec[i - 1]) * mpre[i] for i in range(1, len(mrec)))


# ---------------------------------------------------------------- hand-worked examples


def test_single_frame_hand_worked():
    # GT: three 4 m x 2 m cars on the x axis.
    gt = np.array([car(0.0), car(10.0), car(20.0)])
    # Predictions in input order; IoUs with their GT written out:
    #   p0 score .5 at x=21.5: overlap 2.5x2=5, union 11 -> IoU 5/11 = 0.4545 with GT2
    #   p1 score .9 at x=0   : IoU 1 with GT0
    #   p2 score .8 at x=10.8: overlap 3.2x2=6.4, union 9.6 -> IoU 2/3 with GT1
    #   p3 score .7 at x=50  : no overlap
    #   p4 score .6 at x=0.4 : duplicate of GT0 (already taken) -> best remaining IoU 0
    pred = np.array([car(21.5), car(0.0), car(10.8), car(50.0), car(0.4)])
    scores = np.array([0.5, 0.9, 0.8, 0.7, 0.6])
    stats = frame_stats(pred, scores, gt, THRESHOLDS)
    np.testing.assert_array_equal(stats.scores, [0.9, 0.8, 0.7, 0.6, 0.5])
    expected_tp = np.array(
        [[1, 1, 0, 0, 1],  # IoU >= 0.3
         [1, 1, 0, 0, 0],  # IoU >= 0.5
         [1, 0, 0, 0, 0]],  # IoU >= 0.7
        dtype=bool,
    )
    np.testing.assert_array_equal(stats.tp, expected_tp)
    np.testing.assert_array_equal(stats.fp, ~expected_tp)
    assert stats.n_gt == 3
    # Precision / recall steps, by descending score, n_gt = 3:
    # @0.3 cum tp 1,2,2,2,3 -> recall 1/3,2/3,2/3,2/3,1; precision 1,1,2/3,1/2,3/5
    #      monotone precision 1,1,.6,.6,.6 -> AP = 1/3*1 + 1/3*1 + 1/3*0.6 = 0.8667
    # @0.5 cum tp 1,2,2,2,2 -> precision 1,1,2/3,1/2,2/5 -> AP = 2/3
    # @0.7 cum tp 1,1,1,1,1 -> precision 1,1/2,1/3,1/4,1/5 -> AP = 1/3
    steps = {
        0.3: ([1 / 3, 2 / 3, 2 / 3, 2 / 3, 1.0], [1.0, 1.0, 2 / 3, 1 / 2, 3 / 5]),
        0.5: ([1 / 3, 2 / 3, 2 / 3, 2 / 3, 2 / 3], [1.0, 1.0, 2 / 3, 1 / 2, 2 / 5]),
        0.7: ([1 / 3] * 5, [1.0, 1 / 2, 1 / 3, 1 / 4, 1 / 5]),
    }
    expected_ap = {0.3: 1 / 3 + 1 / 3 + 0.6 / 3, 0.5: 2 / 3, 0.7: 1 / 3}
    ap = frame_ap(pred, scores, gt, THRESHOLDS)
    for thr in THRESHOLDS:
        assert voc_ap_from_steps(*steps[thr]) == pytest.approx(expected_ap[thr], abs=1e-15)
        assert ap[thr] == pytest.approx(expected_ap[thr], abs=1e-12)


def test_precision_is_made_monotone_from_the_right():
    gt = np.array([car(0.0), car(10.0), car(20.0)])
    pred = np.array([car(0.0), car(40.0), car(10.0), car(20.0)])
    # Order .9 TP, .8 FP, .7 TP, .6 TP; recall 1/3, 1/3, 2/3, 1; precision 1, 1/2, 2/3, 3/4
    # monotone precision 1, 3/4, 3/4, 3/4 -> AP = 1/3 + 1/3 * 3/4 + 1/3 * 3/4 = 5/6
    # (without the interpolation it would be 1/3 + 2/9 + 1/4 = 0.8056)
    steps = ([1 / 3, 1 / 3, 2 / 3, 1.0], [1.0, 1 / 2, 2 / 3, 3 / 4])
    assert voc_ap_from_steps(*steps) == pytest.approx(5 / 6, abs=1e-15)
    ap = frame_ap(pred, [0.9, 0.8, 0.7, 0.6], gt, (0.5,))
    assert ap[0.5] == pytest.approx(5 / 6, abs=1e-12)


def test_greedy_matching_takes_max_iou_of_remaining_gt():
    # One prediction between two GTs overlaps GT1 more; the second prediction then only
    # has GT0 left even though it overlaps GT1 better.
    gt = np.array([car(0.0), car(3.0)])
    pred = np.array([car(2.2), car(2.6)])
    stats = frame_stats(pred, [0.9, 0.8], gt, (0.1,))
    # p0 (x=2.2): IoU with GT0 overlap 1.8 -> 3.6/12.4, with GT1 overlap 3.2 -> 6.4/9.6 -> GT1
    # p1 (x=2.6): GT1 gone; GT0 overlap 1.4 -> 2.8/13.2 = 0.212 >= 0.1 -> TP
    np.testing.assert_array_equal(stats.tp, [[True, True]])
    stats = frame_stats(pred, [0.9, 0.8], gt, (0.25,))
    np.testing.assert_array_equal(stats.tp, [[True, False]])


def test_multi_frame_global_sort_hand_worked():
    acc = APAccumulator(THRESHOLDS)
    acc.add_frame([car(0.0)], [0.9], [car(0.0)])  # frame A: TP .9
    acc.add_frame([car(30.0), car(10.0)], [0.95, 0.6], [car(0.0), car(10.0)])  # B: FP .95, TP .6
    acc.add_frame(np.zeros((0, 7)), [], [car(5.0)])  # C: a GT, no predictions
    acc.add_frame([car(7.0)], [0.8], np.zeros((0, 7)))  # D: no GT, FP .8
    assert acc.n_frames == 4 and acc.n_gt == 4
    # Global order .95 FP, .9 TP, .8 FP, .6 TP; n_gt = 4
    # recall 0, 1/4, 1/4, 1/2; precision 0, 1/2, 1/3, 1/2 -> monotone 1/2 everywhere
    # AP = 1/4 * 1/2 + 1/4 * 1/2 = 0.25
    expected = voc_ap_from_steps([0.0, 0.25, 0.25, 0.5], [0.0, 0.5, 1 / 3, 0.5])
    assert expected == pytest.approx(0.25, abs=1e-15)
    for value in acc.ap().values():
        assert value == pytest.approx(0.25, abs=1e-12)


def test_nan_and_zero_rules():
    empty = np.zeros((0, 7))
    assert all(math.isnan(v) for v in frame_ap(empty, [], empty).values())
    assert frame_ap(empty, [], [car(0.0)]) == dict.fromkeys(THRESHOLDS, 0.0)
    assert frame_ap([car(0.0)], [0.5], empty) == dict.fromkeys(THRESHOLDS, 0.0)
    assert all(math.isnan(v) for v in APAccumulator().ap().values())
    perfect = frame_ap([car(0.0), car(9.0)], [0.3, 0.4], [car(9.0), car(0.0)])
    assert perfect == dict.fromkeys(THRESHOLDS, 1.0)


def test_add_stats_equals_add_frame_and_checks_thresholds():
    rng = np.random.default_rng(3)
    frames = [random_frame(rng) for _ in range(5)]
    by_frame, by_stats = APAccumulator(), APAccumulator()
    for pred, scores, gt in frames:
        stats = by_frame.add_frame(pred, scores, gt)
        by_stats.add_stats(FrameStats(stats.scores, stats.tp.tolist(), stats.fp, stats.n_gt))
    assert by_frame.ap() == by_stats.ap()
    with pytest.raises(ValueError, match="thresholds"):
        APAccumulator((0.5,)).add_stats(stats)
    with pytest.raises(ValueError, match="stats"):
        APAccumulator().add_stats({"scores": []})


# ---------------------------------------------------------------- reference implementation


def shapely_iou(box_a: np.ndarray, box_b: np.ndarray) -> float:
    poly_a = shapely.Polygon(box_corners_bev(box_a[None])[0])
    poly_b = shapely.Polygon(box_corners_bev(box_b[None])[0])
    union = poly_a.union(poly_b).area
    return poly_a.intersection(poly_b).area / union if union > 0 else 0.0


def reference_ap(frames: list, thr: float) -> float:
    """Plain loops + shapely, written from the protocol text (OpenCOOD style)."""
    pooled, n_gt = [], 0
    for pred, scores, gt in frames:
        remaining = list(gt)
        n_gt += len(gt)
        for k in sorted(range(len(scores)), key=lambda i: -scores[i]):
            ious = [shapely_iou(pred[k], g) for g in remaining]
            if not ious or max(ious) < thr:
                pooled.append((scores[k], 0))
                continue
            pooled.append((scores[k], 1))
            remaining.pop(ious.index(max(ious)))
    if n_gt == 0:
        return math.nan if not pooled else 0.0
    if not pooled:
        return 0.0
    pooled.sort(key=lambda item: -item[0])
    recall, precision, tp = [], [], 0
    for rank, (_, hit) in enumerate(pooled, start=1):
        tp += hit
        recall.append(tp / n_gt)
        precision.append(tp / rank)
    return voc_ap_from_steps(recall, precision)


def random_frame(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """GT cars; predictions = jittered copies of some GTs plus false positives; tied scores."""
    n_gt = int(rng.integers(0, 8))
    gt = np.array([car(*rng.uniform([-40, -15], [40, 15]), yaw=rng.uniform(-np.pi, np.pi),
                       length=rng.uniform(3.5, 5.0), width=rng.uniform(1.6, 2.2))
                   for _ in range(n_gt)]).reshape(-1, 7)
    detected = gt[rng.random(n_gt) < 0.8].copy()
    detected[:, :2] += rng.normal(0.0, 0.6, (len(detected), 2))
    detected[:, 6] += rng.normal(0.0, 0.2, len(detected))
    duplicates = detected[rng.random(len(detected)) < 0.2]
    n_fp = int(rng.integers(0, 3))
    false_pos = np.array([car(*rng.uniform([-40, -15], [40, 15])) for _ in range(n_fp)])
    pred = np.concatenate([detected, duplicates, false_pos.reshape(-1, 7)])
    if rng.random() < 0.15:
        pred = pred[:0]
    scores = np.round(rng.uniform(0.05, 1.0, len(pred)), 1)  # ties on purpose
    return pred, scores, gt


def test_ap_matches_loop_and_shapely_reference():
    rng = np.random.default_rng(12345)
    frames = [random_frame(rng) for _ in range(60)]
    frames.append((np.zeros((0, 7)), np.zeros(0), np.array([car(1.0)])))  # GT, no predictions
    frames.append((np.array([car(2.0)]), np.array([0.7]), np.zeros((0, 7))))  # no GT
    acc = APAccumulator(THRESHOLDS)
    for pred, scores, gt in frames:
        acc.add_frame(pred, scores, gt)
        single = frame_ap(pred, scores, gt, THRESHOLDS)
        for thr in THRESHOLDS:
            expected = reference_ap([(pred, scores, gt)], thr)
            assert single[thr] == pytest.approx(expected, abs=1e-12, nan_ok=True)
    batched = APAccumulator(THRESHOLDS)
    batched.add_frames(frames)
    assert batched.n_frames == acc.n_frames and batched.n_gt == acc.n_gt
    for thr in THRESHOLDS:
        expected = reference_ap(frames, thr)
        assert 0.0 < expected < 1.0
        assert abs(acc.ap()[thr] - expected) <= 1e-12
        assert abs(batched.ap()[thr] - expected) <= 1e-12


def test_add_frames_matches_add_frame_per_frame():
    rng = np.random.default_rng(99)
    frames = [random_frame(rng) for _ in range(40)]
    # Crowded frames: many predictions competing for the same GTs.
    for _ in range(5):
        gt = np.array([car(3.0 * k, yaw=rng.uniform(-0.3, 0.3)) for k in range(6)])
        pred = np.repeat(gt, 3, axis=0)
        pred[:, :2] += rng.normal(0.0, 0.8, (len(pred), 2))
        frames.append((pred, np.round(rng.random(len(pred)), 1), gt))
    thresholds = tuple(np.round(np.arange(0.05, 1.0, 0.05), 2))
    one_by_one, batched = APAccumulator(thresholds), APAccumulator(thresholds)
    for frame in frames:
        one_by_one.add_frame(*frame)
    batched.add_frames(frames)
    assert one_by_one.ap() == batched.ap()
    batched.add_frames([])
    assert batched.n_frames == len(frames)


@pytest.mark.parametrize("dense_max_pairs", [0, 10**9])
def test_kd_tree_and_dense_candidate_searches_agree(monkeypatch, dense_max_pairs):
    """KD-tree only vs dense only: same stats; frames never match each other's boxes."""
    rng = np.random.default_rng(7)
    frames = [random_frame(rng) for _ in range(12)]
    expected = [frame_stats(*frame, THRESHOLDS) for frame in frames]
    monkeypatch.setattr(metrics, "_DENSE_MAX_PAIRS", dense_max_pairs)
    for ours, ref in zip(match_frames(frames, THRESHOLDS), expected, strict=True):
        assert np.array_equal(ours.scores, ref.scores) and np.array_equal(ours.tp, ref.tp)
        assert ours.n_gt == ref.n_gt
    # Predictions in one frame, the same boxes as GT in the next: all false positives.
    boxes = np.array([car(0.0), car(5.0)])
    split = match_frames([(boxes, np.array([0.9, 0.8]), np.zeros((0, 7))),
                          (np.zeros((0, 7)), np.zeros(0), boxes)], THRESHOLDS)
    assert not split[0].tp.any() and split[1].n_gt == 2


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(0.0, 1.0), min_size=1, max_size=12), st.integers(0, 2**31 - 1))
def test_ap_properties(scores, seed):
    """AP in [0, 1]; perfect detections give 1 whatever the scores; frame order is irrelevant."""
    rng = np.random.default_rng(seed)
    gt = np.array([car(10.0 * k, yaw=rng.uniform(-3, 3)) for k in range(len(scores))])
    assert frame_ap(gt, scores, gt) == dict.fromkeys(THRESHOLDS, 1.0)
    frames = [random_frame(rng) for _ in range(4)]
    forward, backward = APAccumulator(), APAccumulator()
    for frame in frames:
        forward.add_frame(*frame)
    for frame in reversed(frames):
        backward.add_frame(*frame)
    for thr, value in forward.ap().items():
        if not math.isnan(value):
            assert 0.0 <= value <= 1.0
            if len({s for f in frames for s in f[1]}) == sum(len(f[1]) for f in frames):
                assert backward.ap()[thr] == pytest.approx(value, abs=1e-12)


# ---------------------------------------------------------------- range, RPE, success


def test_in_range_mask_uses_all_corners():
    boxes = np.array([
        car(0.0),                      # well inside
        car(8.0),                      # front corners at x = 10: on the boundary, inside
        car(8.5),                      # front corners at 10.5: outside although centre inside
        car(0.0, 4.0, yaw=np.pi / 2),  # rotated: corners reach y = 6 > 5
        car(0.0, 3.0, yaw=np.pi / 2),  # rotated: corners reach y = 5, inside
        car(-20.0),
    ])
    np.testing.assert_array_equal(
        in_range_mask(boxes, (-10.0, 10.0), [-5.0, 5.0]), [True, True, False, False, True, False]
    )
    assert in_range_mask(np.zeros((0, 7)), (-1, 1), (-1, 1)).shape == (0,)


def test_in_range_mask_equals_the_corner_test():
    rng = np.random.default_rng(8)
    n = 4000
    boxes = np.column_stack([rng.uniform(-14, 14, n), rng.uniform(-8, 8, n), np.zeros(n),
                             rng.uniform(0.0, 12.0, n), rng.uniform(0.0, 3.0, n), np.ones(n),
                             rng.uniform(-7, 7, n)])
    corners = box_corners_bev(boxes)
    by_corners = ((corners[..., 0] >= -10) & (corners[..., 0] <= 10)
                  & (corners[..., 1] >= -5) & (corners[..., 1] <= 5)).all(axis=1)
    mask = in_range_mask(boxes, (-10, 10), (-5, 5))
    np.testing.assert_array_equal(mask, by_corners)
    assert 0.1 < mask.mean() < 0.9


def test_relative_pose_error():
    truth = np.array([[1.0, 2.0, np.radians(179.0)], [0.0, 0.0, 0.0], [5.0, 5.0, 0.5]])
    est = np.array([[4.0, 6.0, np.radians(-179.0)], [np.nan] * 3, [5.0, 5.0, 0.5]])
    err = relative_pose_error(est, truth)
    np.testing.assert_allclose(err[0], [5.0, 2.0], atol=1e-12)
    assert np.isnan(err[1]).all()
    np.testing.assert_allclose(err[2], [0.0, 0.0], atol=1e-12)
    partial = relative_pose_error([[0.0, np.nan, 0.0]], [[0.0, 0.0, 0.0]])
    assert np.isnan(partial).all()


def test_success_rate():
    errors = np.array([[0.5, 0.5], [0.9, 1.5], [1.0, 0.1], [np.nan, np.nan], [0.2, 0.99]])
    assert success_rate(errors, 1.0) == pytest.approx(0.5)  # strict <, NaN row ignored
    assert success_rate(errors, 2.0) == pytest.approx(1.0)
    assert math.isnan(success_rate(np.full((3, 2), np.nan), 1.0))
    assert math.isnan(success_rate(np.zeros((0, 2)), 1.0))


# ---------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: frame_stats(np.zeros((2, 6)), [1, 1], np.zeros((0, 7))), "pred_boxes"),
        (lambda: frame_stats([car(0)], [1.0], [car(np.nan)]), "gt_boxes"),
        (lambda: frame_stats([car(0, length=-1)], [1.0], []), "pred_boxes"),
        (lambda: frame_stats([car(0)], [1.0, 2.0], []), "pred_scores"),
        (lambda: frame_stats([car(0)], [np.inf], []), "pred_scores"),
        (lambda: frame_stats([car(0)], [1.0], [], (0.5, 1.5)), "iou_thresholds"),
        (lambda: APAccumulator(()), "iou_thresholds"),
        (lambda: APAccumulator((0.0, 0.5)), "iou_thresholds"),
        (lambda: APAccumulator().add_frames([([car(0)], [1.0], [])] * 2 + [([car(0)], [], [])]),
         r"frames\[2\]\.pred_scores"),
        (lambda: APAccumulator().add_frames([([car(0)], [1.0])]), r"frames\[0\] must be"),
        (lambda: FrameStats([1.0], [[True]], [[True]], 1, (0.5,)), "tp and fp"),
        (lambda: FrameStats([1.0], [[True]], [[False]], 0, (0.5,)), "n_gt"),
        (lambda: FrameStats([1.0, 2.0], [[True]], [[False]], 1, (0.5,)), "tp and fp"),
        (lambda: in_range_mask([car(0)], (1.0, -1.0), (-1, 1)), "x_range"),
        (lambda: in_range_mask([car(0)], (-1, 1), (0, 1, 2)), "y_range"),
        (lambda: relative_pose_error(np.zeros((2, 3)), np.zeros((3, 3))), "estimated and truth"),
        (lambda: relative_pose_error(np.zeros((2, 2)), np.zeros((2, 2))), "estimated"),
        (lambda: relative_pose_error(np.zeros((1, 3)), [[np.inf, 0, 0]]), "truth"),
        (lambda: success_rate(np.zeros((2, 3)), 1.0), "errors"),
        (lambda: success_rate(np.zeros((2, 2)), 0.0), "lam"),
        (lambda: success_rate(-np.ones((2, 2)), 1.0), "errors"),
    ],
)
def test_bad_input_raises_value_error(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_scalar_average_precision_is_the_one_row_case():
    from roco_env.metrics import average_precision, average_precisions

    scores = np.array([0.9, 0.8, 0.7, 0.6])
    tp = np.array([True, False, True, True])
    # Hand-worked VOC all-point AP with 4 GT: recall steps 1/4 at precision 1,
    # then 2/4 and 3/4 at the monotone precision 3/4 -> 1/4 + 2/4 * 3/4 = 0.625.
    assert average_precision(scores, tp, 4) == pytest.approx(0.625, abs=1e-12)
    assert average_precision(scores, tp, 4) == average_precisions(scores, tp[None], 4)[0]
