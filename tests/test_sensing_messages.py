"""Messages: collaborator selection and what a message carries (no truth)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import car, make_state

from roco_env.comm import instant_inbox
from roco_env.scenario import DetectorConfig
from roco_env.sensing import Message, compute_visibility, make_detector, select_collaborators

# Agents at distances 0 (ego), 50, 10, 90, 30, 69.9 from the ego.
POSES = [[0, 0, 0], [50, 0, 1], [0, 10, 2], [90, 0, 0], [-30, 0, 0], [0, -69.9, 0]]


def scene():
    return make_state([car(20, 5), car(40, -5)], POSES)


def test_collaborators_within_range_nearest_first_capped():
    state = scene()
    assert select_collaborators(state, 0, 5) == [2, 4, 1, 5]
    assert select_collaborators(state, 0, 2) == [2, 4]
    assert select_collaborators(state, 0, 0) == []
    assert select_collaborators(state, 0, 5, comm_range=40.0) == [2, 4]
    assert select_collaborators(state, 3, 5) == [1]


@pytest.mark.parametrize("kwargs, name", [
    ({"ego_index": 6, "max_collaborators": 5}, "ego_index"),
    ({"ego_index": 0, "max_collaborators": -1}, "max_collaborators"),
    ({"ego_index": 0, "max_collaborators": 5, "comm_range": 0.0}, "comm_range"),
])
def test_bad_selection_inputs_rejected(kwargs, name):
    with pytest.raises(ValueError, match=name):
        select_collaborators(scene(), **kwargs)


def test_an_inbox_carries_reported_poses_and_own_frame_detections_only():
    state = scene()
    dets = make_detector(DetectorConfig()).detect(state, compute_visibility(state),
                                                 np.random.default_rng(0))
    reported = np.asarray(POSES, float) + 0.5
    inbox = instant_inbox(state, reported, dets, max_collaborators=3)
    assert [[d.scan.sender for d in row] for row in inbox] == [
        select_collaborators(state, ego, 3) for ego in range(len(POSES))]
    assert [d.scan.sender for d in inbox[0]] == [2, 4, 1]
    for delivery, j in zip(inbox[0], (2, 4, 1), strict=True):
        assert delivery.new and delivery.age == 0.0 and delivery.scan.time == state.time
        np.testing.assert_array_equal(delivery.scan.reported_pose, reported[j])
        np.testing.assert_array_equal(delivery.scan.boxes, dets[j].boxes)
        np.testing.assert_array_equal(delivery.scan.uncertainty, dets[j].uncertainty)
        np.testing.assert_array_equal(delivery.scan.scores, dets[j].scores)
        assert delivery.scan.encoder_map is None
    assert {f.name for f in dataclasses.fields(Message)} == {
        "sender", "reported_pose", "boxes", "uncertainty", "scores"}
