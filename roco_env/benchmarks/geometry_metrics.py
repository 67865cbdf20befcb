"""Benchmark: vectorised BEV IoU and dataset AP against plain shapely loops.

Measured in one process: ``bev_iou`` on 200 x 200 boxes (a realistic scene of
200 vehicles spread over 200 m x 80 m, and the worst case where all 40,000
pairs overlap) against a per-pair shapely loop, and a dataset AP evaluation
(``APAccumulator``) against a loop-and-shapely implementation of the same
protocol. Results are asserted identical before the speed ratios are reported.
"""

from __future__ import annotations

import numpy as np
import shapely

from roco_env.benchmarks._timing import median_seconds
from roco_env.geometry import bev_iou, box_corners_bev
from roco_env.metrics import DEFAULT_IOU_THRESHOLDS, APAccumulator, LabelledFrame


def _vehicles(rng: np.random.Generator, n: int, x_span: float, y_span: float) -> np.ndarray:
    """n car-sized boxes (N, 7) with centres uniform in [-x_span/2, x_span/2] x [...]."""
    boxes = np.empty((n, 7))
    boxes[:, 0] = rng.uniform(-x_span / 2, x_span / 2, n)
    boxes[:, 1] = rng.uniform(-y_span / 2, y_span / 2, n)
    boxes[:, 2] = 0.8
    boxes[:, 3] = rng.uniform(3.8, 5.2, n)
    boxes[:, 4] = rng.uniform(1.7, 2.1, n)
    boxes[:, 5] = 1.6
    boxes[:, 6] = rng.uniform(-np.pi, np.pi, n)
    return boxes


def _detections(rng: np.random.Generator, truth: np.ndarray) -> np.ndarray:
    """Noisy copies of ``truth`` (centre 0.3 m, yaw 0.05 rad)."""
    pred = truth.copy()
    pred[:, :2] += rng.normal(0.0, 0.3, (len(truth), 2))
    pred[:, 6] += rng.normal(0.0, 0.05, len(truth))
    return pred


def shapely_iou_loop(boxes_a: np.ndarray, boxes_b: np.ndarray) -> np.ndarray:
    """Baseline: one shapely intersection per pair, (N, M)."""
    polys_a = [shapely.Polygon(c) for c in box_corners_bev(boxes_a)]
    polys_b = [shapely.Polygon(c) for c in box_corners_bev(boxes_b)]
    iou = np.zeros((len(polys_a), len(polys_b)))
    for i, pa in enumerate(polys_a):
        for j, pb in enumerate(polys_b):
            inter = pa.intersection(pb).area
            union = pa.area + pb.area - inter
            iou[i, j] = inter / union if union > 0 else 0.0
    return iou


def shapely_ap_loop(frames: list[LabelledFrame], thresholds: tuple[float, ...]) -> dict[float, float]:
    """Baseline: the OpenCOOD protocol with Python loops and shapely IoU.

    Like OpenCOOD's evaluation, the matching (and its IoUs) is redone per threshold.
    """
    result = {}
    for thr in thresholds:
        pooled, n_gt = [], 0
        for pred, scores, gt in frames:
            remaining = [shapely.Polygon(c) for c in box_corners_bev(gt)]
            n_gt += len(remaining)
            for k in sorted(range(len(scores)), key=lambda i: -scores[i]):
                poly = shapely.Polygon(box_corners_bev(pred[k : k + 1])[0])
                ious = [poly.intersection(g).area / poly.union(g).area for g in remaining]
                if ious and max(ious) >= thr:
                    remaining.pop(ious.index(max(ious)))
                    pooled.append((scores[k], 1))
                else:
                    pooled.append((scores[k], 0))
        pooled.sort(key=lambda item: -item[0])
        tp = np.cumsum([hit for _, hit in pooled])
        recall = [0.0, *(tp / n_gt), 1.0]
        precision = [0.0, *(tp / np.arange(1, len(tp) + 1)), 0.0]
        for i in range(len(precision) - 2, -1, -1):
            precision[i] = max(precision[i], precision[i + 1])
        result[thr] = sum(
            (recall[i] - recall[i - 1]) * precision[i] for i in range(1, len(recall))
        )
    return result


def _frames(rng: np.random.Generator, n_frames: int) -> list[LabelledFrame]:
    """Frames of 0-30 GT vehicles; 85% detected with noise, plus 0-4 false positives."""
    frames = []
    for _ in range(n_frames):
        gt = _vehicles(rng, int(rng.integers(0, 31)), 200.0, 80.0)
        pred = np.concatenate([
            _detections(rng, gt[rng.random(len(gt)) < 0.85]),
            _vehicles(rng, int(rng.integers(0, 5)), 200.0, 80.0),
        ])
        frames.append((pred, rng.uniform(0.05, 1.0, len(pred)), gt))
    return frames


def _batched_ap(frames: list[LabelledFrame]) -> dict[float, float]:
    acc = APAccumulator(DEFAULT_IOU_THRESHOLDS)
    acc.add_frames(frames)
    return acc.ap()


def _per_frame_ap(frames: list[LabelledFrame]) -> dict[float, float]:
    acc = APAccumulator(DEFAULT_IOU_THRESHOLDS)
    for frame in frames:
        acc.add_frame(*frame)
    return acc.ap()


def _iou_lines(name: str, boxes_a: np.ndarray, boxes_b: np.ndarray, repeats: int) -> list[str]:
    ours = bev_iou(boxes_a, boxes_b)
    reference = shapely_iou_loop(boxes_a, boxes_b)
    diff = float(np.max(np.abs(ours - reference)))
    assert diff < 1e-9, f"bev_iou differs from shapely by {diff}"
    fast = median_seconds(lambda: bev_iou(boxes_a, boxes_b), repeats=5 * repeats, warmup=1)
    slow = median_seconds(lambda: shapely_iou_loop(boxes_a, boxes_b), repeats=repeats, warmup=0)
    return [
        f"bev_iou 200x200 {name} ({np.count_nonzero(ours)} overlapping pairs): "
        f"numpy {fast * 1e3:.2f} ms, shapely loop {slow * 1e3:.1f} ms -> {slow / fast:.1f}x "
        f"(max |diff| {diff:.1e})"
    ]


def run(quick: bool) -> list[str]:
    """Medians and speed ratios (see module docstring); quick uses fewer frames/repeats."""
    rng = np.random.default_rng(0)
    repeats = 1 if quick else 3
    truth = _vehicles(rng, 200, 200.0, 80.0)
    lines = _iou_lines("realistic 200 m x 80 m", truth, _detections(rng, truth), repeats)
    crowd_a = _vehicles(rng, 200, 1.0, 1.0)
    crowd_b = _vehicles(rng, 200, 1.0, 1.0)
    lines += _iou_lines("worst case, all overlap", crowd_a, crowd_b, repeats)

    n_frames = 200 if quick else 1000
    frames = _frames(rng, n_frames)
    reference = shapely_ap_loop(frames, DEFAULT_IOU_THRESHOLDS)
    slow = median_seconds(
        lambda: shapely_ap_loop(frames, DEFAULT_IOU_THRESHOLDS), repeats=repeats, warmup=0
    )
    n_pred = sum(len(f[1]) for f in frames)
    n_gt = sum(len(f[2]) for f in frames)
    for name, evaluate in (("add_frames (batched)", _batched_ap),
                           ("add_frame per frame", _per_frame_ap)):
        ours = evaluate(frames)
        for thr in DEFAULT_IOU_THRESHOLDS:
            assert abs(ours[thr] - reference[thr]) <= 1e-12, (name, thr, ours[thr], reference[thr])
        fast = median_seconds(lambda ev=evaluate: ev(frames), repeats=repeats + 2, warmup=1)
        aps = ", ".join(f"AP@{thr}={ours[thr]:.4f}" for thr in DEFAULT_IOU_THRESHOLDS)
        lines.append(
            f"AP over {n_frames} frames ({n_pred} predictions, {n_gt} GT; {aps}): "
            f"APAccumulator.{name} {fast * 1e3:.1f} ms, loop+shapely {slow * 1e3:.0f} ms -> "
            f"{slow / fast:.1f}x (identical to 1e-12)"
        )
    return lines
