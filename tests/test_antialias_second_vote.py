"""The second translation vote at the reported rotation (roco_env.policies.hypotheses,
step 1): it fires when the heading vote lands more than SECOND_VOTE_DEG from the reported
rotation, and only then."""

import numpy as np
import pytest

import roco_env.policies.hypotheses as hypotheses
from roco_env.policies.hypotheses import EvidenceParams, box_set, generate_hypotheses
from roco_env.policies.landmarks import UncertaintyParams, prepare_inputs
from roco_env.testing.constructed_scenes import make_scene, pose_error


def _road_sets(heading_bias_deg: float):
    """A three-lane road along x, every car heading along it (gaps 1-6 m), seen by an ego
    beside it at x = 0 and a collaborator 118 m down the road facing back (both 100 m
    range), the collaborator reported 0.3 m / 0.3 deg off; its boxes' headings turned by
    ``heading_bias_deg`` (deg), which moves the heading vote and nothing else. Returns
    the ego's and the collaborator's box sets, the reported and the true pose T_{1->0}."""
    rng = np.random.default_rng(3)
    cars = []
    for lane in (0.0, 3.5, 7.0):
        x = -20.0
        while x < 140.0:
            cars.append([x, lane, 0.8, 4.5, 1.9, 1.6, 0.0])
            x += 4.5 + rng.uniform(1.0, 6.0)
    agents = np.array([[0.0, -6.0, 0.0], [118.0, 12.0, np.pi]])
    scene = make_scene(np.array(cars), agents, [pose_error(0.3, 0.3)], sensor_range=100.0,
                       noise=(0.05, 0.05, 0.01), rng=rng)
    scene.collab_boxes[0][:, 6] += np.deg2rad(heading_bias_deg)
    inputs = prepare_inputs(*scene.args(), UncertaintyParams())
    boxes = [scene.ego_boxes, *scene.collab_boxes]
    sets = [box_set(b, inputs.poses[a], inputs.information[a]) for a, b in enumerate(boxes)]
    return sets[0], sets[1], scene.reported[0], scene.true[0]


def _single_vote(ego, collab, reported, monkeypatch):
    """The hypotheses of the heading vote's rotation alone (no second vote)."""
    with monkeypatch.context() as m:
        m.setattr(hypotheses, "SECOND_VOTE_DEG", 180.0)
        return generate_hypotheses(ego, collab, reported, EvidenceParams())


def _yaw_off_deg(poses: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """|yaw difference| (deg) of each pose (H, 3) from ``pose`` (3,)."""
    return np.rad2deg(np.abs(np.angle(np.exp(1j * (poses[:, 2] - pose[2])))))


def test_heading_vote_off_adds_the_reported_rotations_vote(monkeypatch):
    """Headings turned by 4 deg: the heading vote lands 4 deg off, so every peak of its
    translation vote is metres from the truth; the second vote, at the reported rotation,
    adds a hypothesis within a metre of it, after the first vote's peaks."""
    ego, collab, reported, true = _road_sets(4.0)
    single = _single_vote(ego, collab, reported, monkeypatch)
    got = generate_hypotheses(ego, collab, reported, EvidenceParams())
    assert (_yaw_off_deg(single, reported) > hypotheses.SECOND_VOTE_DEG).all()
    assert (np.hypot(*(single[:, :2] - true[:2]).T) > 1.5).all()
    np.testing.assert_array_equal(got[: single.shape[0]], single)
    second = got[single.shape[0]:]
    assert 0 < second.shape[0] <= EvidenceParams().max_hypotheses
    np.testing.assert_array_equal(second[:, 2], np.full(second.shape[0], reported[2]))
    assert np.hypot(*(second[:, :2] - true[:2]).T).min() < 1.0


@pytest.mark.parametrize("bias_deg", [0.0, 0.5])
def test_heading_vote_near_the_reported_rotation_adds_nothing(monkeypatch, bias_deg):
    """Headings as detected (or turned by 0.5 deg): the heading vote lands within
    SECOND_VOTE_DEG of the reported rotation and the hypotheses are its vote's alone."""
    ego, collab, reported, _ = _road_sets(bias_deg)
    got = generate_hypotheses(ego, collab, reported, EvidenceParams())
    assert (_yaw_off_deg(got, reported) <= hypotheses.SECOND_VOTE_DEG).all()
    np.testing.assert_array_equal(got, _single_vote(ego, collab, reported, monkeypatch))
