"""Messages: collaborator selection and what a message carries (no truth)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from conftest import car, make_state

from roco_env.scenario import DetectorConfig
from roco_env.sensing import (
    Message,
    build_messages,
    compute_visibility,
    make_detector,
    select_collaborators,
)

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


def test_messages_carry_reported_pose_and_own_frame_detections_only():
    state = scene()
    dets = make_detector(DetectorConfig()).detect(state, compute_visibility(state),
                                                 np.random.default_rng(0))
    reported = np.asarray(POSES, float) + 0.5
    feats = [torch.full((3, 4, 4), float(i)) for i in range(len(POSES))]
    msgs = build_messages(state, 0, reported, dets, max_collaborators=3, features=feats)
    assert [m.sender for m in msgs] == ["cav_2", "cav_4", "cav_1"]
    for msg, j in zip(msgs, (2, 4, 1), strict=True):
        np.testing.assert_array_equal(msg.reported_pose, reported[j])
        np.testing.assert_array_equal(msg.boxes, dets[j].boxes)
        np.testing.assert_array_equal(msg.uncertainty, dets[j].uncertainty)
        np.testing.assert_array_equal(msg.scores, dets[j].scores)
        assert torch.equal(msg.features, feats[j])
    assert {f.name for f in dataclasses.fields(Message)} == {
        "sender", "reported_pose", "boxes", "uncertainty", "scores", "features"}
    assert build_messages(state, 0, reported, dets, 3)[0].features is None


def test_bad_message_inputs_rejected():
    state = scene()
    dets = make_detector(DetectorConfig()).detect(state, compute_visibility(state),
                                                 np.random.default_rng(0))
    with pytest.raises(ValueError, match="reported_poses"):
        build_messages(state, 0, np.zeros((2, 3)), dets, 3)
    with pytest.raises(ValueError, match="detections"):
        build_messages(state, 0, np.zeros((6, 3)), dets[:2], 3)
