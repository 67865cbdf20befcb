"""Detector model: presets, exact ideal boxes, noise statistics, calibration, clutter."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import bus, car, make_state

from roco_env.geometry import se2_inverse, transform_boxes, wrap_angle
from roco_env.scenario import DetectorConfig
from roco_env.sensing import PRESETS, compute_visibility, make_detector


def ring_scene(n: int = 24, radius: float = 35.0, pose=(5.0, -3.0, 0.7)):
    """n cars on a circle around one CAV, plus a car half hidden behind a bus.

    Built in the agent frame, then placed in the world with the agent's pose.
    """
    angles = 2 * np.pi * (np.arange(n) + 0.5) / n
    local = [car(radius * np.cos(a), radius * np.sin(a), a + 0.3) for a in angles]
    local += [car(60, 0, np.pi / 2), bus(45, 6, np.pi / 2)]
    return make_state(transform_boxes(np.array(local), np.array(pose)), [pose])


def detector(preset: str = "realistic", **params):
    return make_detector(DetectorConfig(preset=preset, params=params))


def test_ideal_reproduces_exact_boxes_of_visible_objects_in_agent_frame():
    state = make_state([car(20, 5, 0.3), bus(40, 5, 0.3), car(60, 5, 0.3), car(-25, -10, 2.0),
                        car(0, 0)], [[0, 0, 0.4]], own_ids=[4])
    vis = compute_visibility(state)
    (dets,) = detector("ideal").detect(state, vis, np.random.default_rng(0))
    expected_ids = np.flatnonzero(vis.visible[0])
    assert set(expected_ids) == {0, 1, 3}  # 2 hidden by the bus, 4 is the agent itself
    order = np.argsort(dets.object_ids)
    np.testing.assert_array_equal(dets.object_ids[order], expected_ids)
    truth = transform_boxes(state.object_boxes[expected_ids], se2_inverse(state.agent_poses[0]))
    np.testing.assert_allclose(dets.boxes[order], truth, atol=1e-12)
    assert np.all(dets.scores == 1.0)
    assert np.all((dets.uncertainty > 0) & (dets.uncertainty < 0.1))


def _matched_errors(preset_params: dict, repeats: int = 150):
    """Errors (x, y, yaw) of true detections in the agent frame over many seeds."""
    state = ring_scene()
    vis = compute_visibility(state)
    det = detector(**preset_params)
    truth = transform_boxes(state.object_boxes, se2_inverse(state.agent_poses[0]))
    errs, uncs, fracs, dists = [], [], [], []
    rng = np.random.default_rng(42)
    for _ in range(repeats):
        (d,) = det.detect(state, vis, rng)
        ids = d.object_ids
        t = truth[ids]
        yaw_err = wrap_angle(d.boxes[:, 6] - t[:, 6])
        errs.append(np.column_stack([d.boxes[:, :2] - t[:, :2], yaw_err]))
        uncs.append(d.uncertainty)
        fracs.append(vis.fraction[0, ids])
        dists.append(np.hypot(t[:, 0], t[:, 1]))
    return (np.concatenate(errs), np.concatenate(uncs), np.concatenate(fracs),
            np.concatenate(dists))


EXACT = {"p_max": 1.0, "returns_50": 0.0, "flip_prob": 0.0, "fp_rate": 0.0}


def test_realistic_errors_match_configured_sigmas_and_are_calibrated():
    params = {**EXACT, "sigma_xy": 0.1, "sigma_xy_per_m": 0.004, "sigma_xy_occlusion": 0.5,
              "sigma_yaw": 0.03, "sigma_yaw_per_m": 0.001, "sigma_yaw_occlusion": 0.2}
    err, unc, frac, dist = _matched_errors(params)
    assert np.any(frac < 0.9)  # some detections are partly occluded
    sigma_xy = 0.1 + 0.004 * dist + 0.5 * (1 - frac)
    sigma_yaw = 0.03 + 0.001 * dist + 0.2 * (1 - frac)
    for axis, sigma in ((0, sigma_xy), (1, sigma_xy), (2, sigma_yaw)):
        assert np.std(err[:, axis] / sigma) == pytest.approx(1.0, rel=0.1)
        assert np.std(err[:, axis] / unc[:, axis]) == pytest.approx(1.0, rel=0.1)
        assert abs(np.mean(err[:, axis] / sigma)) < 0.1
    np.testing.assert_allclose(unc[:, 0], sigma_xy, rtol=1e-9)


def test_calibration_factor_scales_reported_uncertainty_only():
    err, unc, _, _ = _matched_errors({**EXACT, "calibration": 2.0}, repeats=60)
    assert np.std(err[:, 0] / unc[:, 0]) == pytest.approx(0.5, rel=0.1)


def test_heading_flip_rate():
    params = {**EXACT, "flip_prob": 0.2, "sigma_yaw": 0.01, "sigma_yaw_per_m": 0.0,
              "sigma_yaw_occlusion": 0.0}
    err, _, _, _ = _matched_errors(params, repeats=60)
    assert np.mean(np.abs(err[:, 2]) > np.pi / 2) == pytest.approx(0.2, abs=0.03)


def test_false_positive_rate_and_shape():
    state = make_state(np.zeros((0, 7)), [[10, 10, 1.0]], ranges=[60.0])
    vis = compute_visibility(state)
    det = detector(fp_rate=2.5, fp_score_max=0.3)
    rng = np.random.default_rng(7)
    frames = [det.detect(state, vis, rng)[0] for _ in range(2000)]
    counts = np.array([len(f.scores) for f in frames])
    assert counts.mean() == pytest.approx(2.5, rel=0.05)
    assert counts.var() == pytest.approx(2.5, rel=0.15)  # Poisson
    boxes = np.concatenate([f.boxes for f in frames])
    scores = np.concatenate([f.scores for f in frames])
    assert np.all(np.concatenate([f.object_ids for f in frames]) == -1)
    assert np.all(np.hypot(boxes[:, 0], boxes[:, 1]) <= 60.0)
    assert np.all((scores > 0) & (scores <= 0.3))
    assert 4.0 < np.median(boxes[:, 3]) < 5.0 and 1.6 < np.median(boxes[:, 4]) < 2.2


def test_detection_probability_rises_with_returns_and_scores_rank_true_above_clutter():
    det = detector()
    p = det.detection_probability(np.array([0.0, 2.0, 10.0, 50.0, 500.0]))
    assert p[0] == 0.0 and np.all(np.diff(p) > 0) and p[-1] > 0.9
    # A crowded street: true detections should mostly outscore clutter (AUC).
    xs = np.arange(10, 70, 7.0)
    boxes = [car(x, y) for x in xs for y in (-3.5, 0.0, 3.5)]
    state = make_state(boxes, [[0, 0, 0]])
    vis = compute_visibility(state)
    rng = np.random.default_rng(1)
    tp, fp = [], []
    for _ in range(100):
        (d,) = det.detect(state, vis, rng)
        tp.append(d.scores[d.object_ids >= 0])
        fp.append(d.scores[d.object_ids < 0])
    tp, fp = np.concatenate(tp), np.concatenate(fp)
    auc = np.mean(tp[:, None] > fp[None, :])
    assert auc > 0.9
    hard = vis.returns[0] < 20
    assert hard.any() and (~hard).any()


def test_seeded_determinism():
    state = ring_scene()
    vis = compute_visibility(state)
    det = detector()
    a = det.detect(state, vis, np.random.default_rng(123))[0]
    b = det.detect(state, vis, np.random.default_rng(123))[0]
    c = det.detect(state, vis, np.random.default_rng(124))[0]
    for name in ("boxes", "uncertainty", "scores", "object_ids"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert a.boxes.shape != c.boxes.shape or not np.array_equal(a.boxes, c.boxes)


def test_never_detects_itself():
    state = make_state([car(0, 0), car(15, 0)], [[0, 0, 0]], own_ids=[0])
    vis = compute_visibility(state)
    for preset in PRESETS:
        for seed in range(20):
            (d,) = detector(preset).detect(state, vis, np.random.default_rng(seed))
            assert 0 not in d.object_ids


def test_invalid_preset_and_params_rejected():
    with pytest.raises(ValueError, match="detector.preset='perfect'.*ideal.*realistic"):
        make_detector(DetectorConfig(preset="perfect"))
    with pytest.raises(ValueError, match="sigma_z'.*allowed:.*sigma_xy"):
        detector(sigma_z=0.1)
    for name, value in (("sigma_xy", -0.1), ("p_max", 1.5), ("fp_rate", float("nan")),
                        ("calibration", 0.0), ("noisy", "yes"), ("flip_prob", "0.1")):
        with pytest.raises(ValueError, match=name):
            detector(**{name: value})


def test_false_positives_stand_on_the_ground_under_the_agent():
    from dataclasses import replace

    flat = make_state(np.zeros((0, 7)), [[10, 10, 1.0]], ranges=[60.0])
    raised = replace(flat, ground_heights=np.array([20.0]))
    det = detector(fp_rate=5.0)

    def fp_boxes(state):
        rng = np.random.default_rng(3)
        return np.concatenate([det.detect(state, compute_visibility(state), rng)[0].boxes
                               for _ in range(20)])

    low, high = fp_boxes(flat), fp_boxes(raised)
    assert low.shape[0] > 0
    np.testing.assert_allclose(high[:, 2], low[:, 2] + 20.0)
    np.testing.assert_allclose(np.delete(high, 2, axis=1), np.delete(low, 2, axis=1))
