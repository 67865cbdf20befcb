"""baselines/learned_select/headroom_c.py and choice_probe.py: the privileged choosers
score every variant on hand rule C's own frames as the env would, and their decisions do
what their docstrings say."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_equal_to_rounding

from roco_env.metrics import APAccumulator
from roco_env.policies.reject_untested import GAP_M
from roco_env.sweeps.cells import build_grid

FOLDER = Path(__file__).resolve().parents[1] / "baselines" / "learned_select"


@pytest.fixture(scope="module")
def scripts():
    """The scripts (they import their siblings by name, as when run from the folder)."""
    sys.path.insert(0, str(FOLDER))
    try:
        import choice_probe
        import env_hook
        import headroom_c
        yield headroom_c, choice_probe, env_hook
    finally:
        sys.path.remove(str(FOLDER))


def test_c_scored_on_its_own_frames_equals_the_played_episode(scripts):
    """Two steps of parking_lot at noise 3.0, seed 0: C's action fused and scored by
    frame_evaluations gives the played episode's AP@0.7 (to rounding; every agent's frame
    seen once), and rejecting every slot scores differently where C kept one."""
    headroom_c, _, _ = scripts
    cell = build_grid(["parking_lot"], [3.0], [headroom_c.RULE_C], [0], 2)[0]
    scored, rejected = APAccumulator(), APAccumulator()
    frames = []

    def on_frame(frame):
        frames.append(frame)
        c, none = frame.evaluate(np.stack([frame.rule,
                                           np.full_like(frame.rule, len(frame.errors))]))
        scored.add_stats(c.stats)
        rejected.add_stats(none.stats)

    played = headroom_c.play_c(cell, list(headroom_c.PAIR), on_frame)
    assert len(frames) == played["frames"] > 0
    assert any((frame.rule < len(frame.errors)).any() for frame in frames)
    assert_equal_to_rounding(scored.ap()[0.7], played["ap70"])
    assert rejected.ap()[0.7] != pytest.approx(played["ap70"], abs=1e-3)


def test_select_decisions_take_each_choice_or_keep_the_reported_pose(scripts):
    _, _, env_hook = scripts
    reported = np.zeros((3, 3))
    poses = np.stack([np.full((3, 3), 1.0), np.full((3, 3), 2.0)])
    (corrected, kept), = env_hook.select_decisions(reported, poses, np.array([[1, 2, 0]]))
    assert kept.tolist() == [True, False, True]
    assert corrected[:, 0].tolist() == [2.0, 0.0, 1.0]


def test_each_variant_changes_only_its_kind_of_slot(scripts):
    """Slots: 0 untested (roco_fallback within 1), 1 tested near (roco_antialias closer),
    2 tested far (roco_fallback closer), 3 tested near where roco (choice 2) is closest;
    C: reject, roco_fallback, roco_antialias, roco_fallback; reject = 3."""
    headroom_c, _, _ = scripts
    errors = np.array([[2.0, 0.1, 0.9, 0.5],
                       [0.5, 0.2, 0.3, 0.4],
                       [3.0, 0.3, 0.8, 0.1]])
    untested = np.array([True, False, False, False])
    gap = np.array([4.0, 0.1, 0.6, 0.2])
    choice_diagnostics = np.zeros((4, 3, GAP_M + 1))
    choice_diagnostics[:, 1, GAP_M] = gap
    rule = headroom_c.rule_c(untested, choice_diagnostics, 3)
    assert rule.tolist() == [3, 1, 0, 1]

    def decide(variant):
        return headroom_c.decide(variant, rule, errors, untested, 1.0, gap).tolist()

    assert decide("c") == [3, 1, 0, 1]
    assert decide("untested_best") == [1, 1, 0, 1]
    assert decide("tested_near_best") == [3, 0, 0, 1]
    assert decide("tested_far_best") == [3, 1, 1, 1]
    assert decide("open_near_best") == [1, 0, 1, 1]
    assert decide("all_best") == [1, 0, 1, 2]


def test_ap_greedy_takes_the_best_option_per_listed_slot_and_keeps_ties(scripts):
    headroom_c, _, _ = scripts
    rule = np.array([0, 1, 2])
    prefer_two = headroom_c.ap_greedy(rule, [0, 1, 2], np.array([0, 1]),
                                      lambda picks: np.sum(picks == 2, axis=1) * 1.0)
    assert prefer_two.tolist() == [2, 2, 2]  # slot 2 not listed, already 2
    flat = headroom_c.ap_greedy(rule, [0, 1, 2], np.arange(3),
                                lambda picks: np.full(len(picks), 0.5))
    assert flat.tolist() == [0, 1, 2]
    nan_lowest = headroom_c.ap_greedy(np.array([0]), [0, 1], np.arange(1),
                                      lambda picks: np.where(picks[:, 0] == 0, np.nan, 0.0))
    assert nan_lowest.tolist() == [1]


def _separable():
    """(inputs (24, 2), labels (24,), held (24,)): the first column separates the labels."""
    labels = np.array([False, True, False, True, True, False] * 4)
    return np.c_[np.where(labels, 1.0, -1.0), np.arange(24.0)], labels, np.arange(24) >= 18


def test_the_logistic_probe_fits_a_separable_label_and_auc_reads_the_ranking(scripts):
    _, choice_probe, _ = scripts
    inputs, labels, held = _separable()
    assert choice_probe.auc(labels, np.arange(24.0) * labels) == 1.0
    assert choice_probe.auc(labels, -np.arange(24.0) * labels) == 0.0
    probe = choice_probe.PROBES["logistic"](inputs, labels, held)
    assert ((probe(inputs) > 0.5) == labels).all()


@pytest.mark.slow
def test_the_mlp_probe_fits_a_separable_label(scripts):
    _, choice_probe, _ = scripts
    inputs, labels, held = _separable()
    probe = choice_probe.PROBES["mlp"](inputs, labels, held)
    assert ((probe(inputs) > 0.5) == labels).all()


def _aligned_observation():
    """An aligned observation (K = 4 box slots, N = 3 collaborator slots, 2 filled) whose
    collaborators' boxes are shown moved by a wrong reported pose: with their true pose,
    slot 0's boxes coincide with the ego's two, slot 1's too plus one far new box.
    Returns (observation, true poses (2, 3))."""
    from roco_env.geometry import se2_inverse, transform_boxes

    own = np.array([[10.0, 0.0, 0.0, 4.5, 1.9, 1.6, 0.1], [20.0, 5.0, 0.0, 4.5, 1.9, 1.6, -1.0]])
    new = np.array([[50.0, 50.0, 0.0, 4.5, 1.9, 1.6, 0.0]])
    true = np.array([[5.0, 2.0, 0.3], [-3.0, 8.0, -0.5]])
    reported = true + [[1.0, -1.0, -0.1], [0.5, 0.5, 0.05]]
    observation = {"boxes": np.zeros((4, 7)), "scores": np.zeros(4), "box_mask": np.zeros(4),
                   "collab_boxes": np.zeros((3, 4, 7)), "collab_scores": np.zeros((3, 4)),
                   "collab_box_mask": np.zeros((3, 4)), "collab_rel_poses": np.zeros((3, 3))}
    observation["boxes"][:2], observation["scores"][:2], observation["box_mask"][:2] = own, 0.9, 1
    for slot, boxes in enumerate([own, np.r_[own, new]]):
        local = transform_boxes(boxes, se2_inverse(true[slot]))
        observation["collab_boxes"][slot, :len(boxes)] = transform_boxes(local, reported[slot])
        observation["collab_scores"][slot, :len(boxes)] = 0.8
        observation["collab_box_mask"][slot, :len(boxes)] = 1
        observation["collab_rel_poses"][slot] = reported[slot]
    return observation, true


def test_slot_features_of_collaborators_whose_boxes_coincide_with_the_egos(scripts):
    """Slot 0's boxes coincide with the ego's: all matched, distance / yaw 0, IoU 1, nothing
    new; the ego's higher scores keep its boxes in late fusion. Slot 1 adds one far box,
    which no other slot has and which late fusion keeps."""
    _, choice_probe, _ = scripts
    slot_features, NAMES = choice_probe.slot_features, choice_probe.NAMES
    observation, true = _aligned_observation()
    rows = slot_features(observation, true, np.array([True, True]), np.array([0, 1]))
    got = [dict(zip(NAMES, row, strict=True)) for row in rows]
    assert got[0] == pytest.approx({
        "boxes": 2, "share_matched": 1, "median_matched_m": 0, "max_matched_m": 0,
        "median_matched_yaw": 0, "mean_matched_iou": 1, "overlap_unmatched": 0, "new": 0,
        "mean_score": 0.8, "min_score": 0.8, "mean_new_score": 0,
        "mean_range_m": got[0]["mean_range_m"], "collaborator_m": np.hypot(5, 2),
        "mean_others": 1, "new_alone": 0, "score_minus_ego": -0.1, "fused_from_slot": 0,
        "fused_replacing_ego": 0, "fused_shift_m": 0, "fused_new": 0}, abs=1e-9)
    assert got[1]["share_matched"] == pytest.approx(2 / 3)
    assert (got[1]["new"], got[1]["new_alone"], got[1]["fused_new"]) == (1, 1, 1)
    assert got[1]["mean_new_score"] == pytest.approx(0.8)
    # slot 0's distance to its boxes: the ego-frame centres seen from the collaborator
    assert got[0]["mean_range_m"] == pytest.approx(np.mean(
        [np.hypot(10 - 5, 0 - 2), np.hypot(20 - 5, 5 - 2)]))
    # moved by the wrong (reported) pose instead, slot 0 no longer coincides
    shown = slot_features(observation, observation["collab_rel_poses"][:2],
                          np.array([True, True]), np.array([0]))[0]
    assert dict(zip(NAMES, shown, strict=True))["median_matched_m"] > 0.5


def test_the_tuned_threshold_maximises_the_gain_of_the_samples_deviated_on(scripts):
    _, choice_probe, _ = scripts
    probabilities = np.array([0.9, 0.8, 0.8, 0.3, 0.1])
    assert choice_probe.tuned_threshold(probabilities, np.array([1.0, -0.5, 2.0, -3.0, 1.0])) == 0.8
    assert choice_probe.tuned_threshold(probabilities, -np.ones(5)) == np.inf
    assert choice_probe.tuned_threshold(probabilities, np.array([1.0, 0, 0, 0, 0])) == 0.9
    assert choice_probe.feature_columns("obs", 30, True).tolist() == list(range(30 - 20))
    assert choice_probe.feature_columns("obs+slot", 30, True).tolist() == list(range(30))
    with pytest.raises(ValueError, match="feature_set"):
        choice_probe.feature_columns("slot", 10, False)
