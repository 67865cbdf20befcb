"""CoAlign as released: clustering rules, hard cases, keep-prior rules, recovery."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from roco_env.metrics import matching_precision_recall, relative_pose_error
from roco_env.policies import make_policy
from roco_env.policies.base import apply_correction
from roco_env.policies.coalign import circular_variance, coalign_align, greedy_clusters
from roco_env.testing.constructed_scenes import (
    make_scene,
    pose_error,
    random_objects,
    to_observation,
)

AGENTS = np.array([[0.0, 0.0, 0.0], [15.0, 5.0, 0.5], [-10.0, 12.0, -1.0]])
ERRORS = np.array([pose_error(0.8, 0.8, 0.3), pose_error(0.8, -0.8, 2.0)])


def sparse_scene(seed=1, count=12, **kwargs):
    objects = random_objects(np.random.default_rng(seed), count, 40.0)
    return make_scene(objects, AGENTS, ERRORS, **kwargs)


def test_recovers_large_pose_error_on_sparse_scene():
    scene = sparse_scene()
    result = coalign_align(*scene.args())
    err = relative_pose_error(result.corrected, scene.true)
    assert result.applied.all() and result.reason == ""
    assert np.all(err[:, 0] < 0.1) and np.all(err[:, 1] < 0.1)
    assert np.all(relative_pose_error(scene.reported, scene.true)[:, 0] > 0.79)
    precision, recall = matching_precision_recall(result, *scene.padded_ids())
    assert precision == 1.0 and recall == 1.0


def test_keeps_prior_with_three_landmarks_or_fewer():
    objects = np.array(
        [
            [5, 0, 0.8, 4.5, 1.9, 1.6, 0.1],
            [12, 6, 0.8, 4.5, 1.9, 1.6, 1.0],
            [3, -9, 0.8, 4.5, 1.9, 1.6, -2.0],
        ]
    )
    scene = make_scene(objects, AGENTS[:2], ERRORS[:1])
    result = coalign_align(*scene.args())
    assert not result.applied.any() and "3 landmarks" in result.reason
    assert np.array_equal(result.corrected, scene.reported)
    assert len(result.matched_pairs) == 3  # the clusters were still found
    more = make_scene(
        np.vstack([objects, [[-6, 4, 0.8, 4.5, 1.9, 1.6, 0.3]]]), AGENTS[:2], ERRORS[:1]
    )
    assert coalign_align(*more.args()).applied.all()


def test_keeps_prior_when_half_the_landmarks_are_hard():
    scene = sparse_scene(count=8)
    flipped = [b.copy() for b in scene.collab_boxes]
    for boxes in flipped:
        boxes[: boxes.shape[0] // 2 + 1, 6] += 1.2  # yaw variance 0.36 rad^2 > 0.2
    result = coalign_align(
        scene.ego_boxes, scene.ego_unc, flipped, scene.collab_unc, scene.reported
    )
    assert not result.applied.any() and "hard" in result.reason


def test_circular_variance_handles_the_pi_wrap():
    assert circular_variance(np.array([np.pi - 0.01, -np.pi + 0.01])) == pytest.approx(1e-4)
    assert circular_variance(np.array([0.0, 1.0])) == pytest.approx(0.25)
    near_pi = np.array([[5, 0, 0, 4, 2, 1.5, np.pi - 0.02]] * 5, dtype=float)
    near_pi[:, 0] = [5, 15, 25, -10, -20]
    wrapped = near_pi.copy()
    wrapped[:, 6] = -np.pi + 0.02
    unc = np.full((5, 3), 0.1)
    result = coalign_align(near_pi, unc, [wrapped], [unc], np.zeros((1, 3)))
    assert result.applied.all()  # 0.04 rad apart, not a hard case


def test_greedy_clustering_is_seeded_in_order_and_not_transitive():
    # ego box 0 at 0 m; collab boxes at 1.0 m and 2.4 m; a second collab box at 1.4 m.
    xy = np.array([[0.0, 0.0], [1.0, 0.0], [2.4, 0.0], [1.4, 0.0]])
    owner = np.array([0, 1, 1, 2])
    clusters = greedy_clusters(xy, owner, 1.5)
    assert [c.tolist() for c in clusters] == [[0, 1, 3]]  # 2.4 m box is not chained in
    # two boxes of the seed's own agent never join its cluster
    assert greedy_clusters(np.array([[0.0, 0.0], [0.5, 0.0]]), np.array([0, 0]), 1.5) == []


def test_unconnected_collaborator_keeps_its_pose():
    scene = sparse_scene()
    far = [scene.collab_boxes[0], scene.collab_boxes[1] + [500, 0, 0, 0, 0, 0, 0]]
    result = coalign_align(scene.ego_boxes, scene.ego_unc, far, scene.collab_unc, scene.reported)
    assert result.applied.tolist() == [True, False]
    assert np.array_equal(result.corrected[1], scene.reported[1])


def test_policy_maps_observation_to_action_and_indices():
    scene = sparse_scene()
    obs = to_observation(scene, max_boxes=20, max_collaborators=4)
    policy = make_policy("coalign")
    action = policy(obs)
    assert action.shape == (4, 3) and action.dtype == np.float32
    assert np.all(action[2:] == 0)
    corrected = apply_correction(obs["collab_rel_poses"], action)[:2]
    assert np.all(relative_pose_error(corrected, scene.true)[:, 0] < 0.1)
    ego_ids, collab_ids = scene.padded_ids()
    pad = np.full((4, 20), -1)
    pad[:2, : collab_ids.shape[1]] = collab_ids
    ego_pad = np.full(20, -1)
    ego_pad[: ego_ids.size] = ego_ids
    assert matching_precision_recall(policy.last_result, ego_pad, pad) == (1.0, 1.0)


def test_bad_parameters_raise():
    scene = sparse_scene()
    with pytest.raises(ValueError, match="cluster_threshold"):
        coalign_align(*scene.args(), cluster_threshold=-1.0)
    with pytest.raises(ValueError, match="unknown coalign parameter"):
        make_policy("coalign", thres=1.5)
    with pytest.raises(ValueError, match="collab_boxes"):
        coalign_align(
            scene.ego_boxes, scene.ego_unc, scene.collab_boxes[:1], scene.collab_unc, scene.reported
        )


def dense_greedy_clusters(xy, owner, threshold):
    """The clustering rule written out over the full distance matrix (test oracle)."""
    dist = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1])
    close = (dist <= threshold) & (owner[:, None] != owner[None, :])
    assigned = np.zeros(len(xy), dtype=bool)
    clusters = []
    for seed in range(len(xy)):
        members = np.nonzero(close[seed] & ~assigned)[0]
        if assigned[seed] or not members.size:
            continue
        assigned[seed] = assigned[members] = True
        clusters.append([seed, *members.tolist()])
    return clusters


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.tuples(st.integers(-12, 12), st.integers(-12, 12), st.integers(0, 3)), max_size=40)
)
def test_greedy_clustering_matches_the_dense_definition(points):
    # half-metre grid: many pairs exactly at the 1.5 m threshold and duplicates
    xy = np.array([p[:2] for p in points], dtype=float).reshape(-1, 2) * 0.5
    owner = np.array([p[2] for p in points], dtype=np.int64)
    got = [c.tolist() for c in greedy_clusters(xy, owner, 1.5)]
    assert got == dense_greedy_clusters(xy, owner, 1.5)


def _near_pi_scene(offset=0.0):
    """Five landmarks whose two boxes are 0.04 rad apart across the +-pi seam."""
    ego = np.array([[5, 0, 0, 4, 2, 1.5, np.pi - 0.02]] * 5, dtype=float)
    ego[:, 0] = [5, 15, 25, -10, -20]
    collab = ego.copy()
    collab[:, 6] = -np.pi + 0.02
    unc = np.full((5, 3), 0.1)
    return ego, unc, [collab], [unc], np.zeros((1, 3))


def test_released_yaw_variance_reproduces_the_frame_dependent_np_var():
    scene = _near_pi_scene()
    circular = coalign_align(*scene)
    released = coalign_align(*scene, yaw_variance="released")
    assert circular.applied.all()
    # np.var of [pi - 0.02, -pi + 0.02] is ~ pi^2: every landmark is "hard"
    assert not released.applied.any() and "5 of 5 landmarks are hard" in released.reason
    # ... unless the world frame is turned so that the yaws no longer straddle the seam
    turned = coalign_align(*scene, yaw_variance="released", ego_yaw=np.pi / 2)
    assert turned.applied.all()
    np.testing.assert_allclose(turned.corrected, circular.corrected, atol=1e-9)


def test_released_yaw_variance_in_the_policy_reads_the_ego_world_yaw():
    ego, unc, collab, cunc, reported = _near_pi_scene()
    k = 8
    obs = {"pose": np.zeros(3, np.float32), "boxes": np.zeros((k, 7), np.float32),
           "uncertainty": np.zeros((k, 3), np.float32), "box_mask": np.zeros(k, np.int8),
           "collab_mask": np.array([1], np.int8), "collab_poses": np.zeros((1, 3), np.float32),
           "collab_rel_poses": np.array([[0.3, -0.2, 0.01]], np.float32),
           "collab_boxes": np.zeros((1, k, 7), np.float32),
           "collab_uncertainty": np.zeros((1, k, 3), np.float32),
           "collab_box_mask": np.zeros((1, k), np.int8)}
    obs["boxes"][:5], obs["uncertainty"][:5], obs["box_mask"][:5] = ego, unc, 1
    obs["collab_boxes"][0, :5], obs["collab_uncertainty"][0, :5] = collab[0], cunc[0]
    obs["collab_box_mask"][0, :5] = 1
    obs["scores"] = np.ones(k, np.float32)
    obs["collab_scores"] = np.ones((1, k), np.float32)
    policy = make_policy("coalign", yaw_variance="released")
    assert np.abs(policy(obs)).max() < 1e-9  # world yaw 0: hard landmarks, priors kept
    obs["pose"][2] = np.pi / 2
    assert np.abs(policy(obs)).max() > 0.1  # the same boxes in a turned world frame
    assert np.abs(make_policy("coalign")(obs)).max() > 0.1
    with pytest.raises(ValueError, match=r"coalign: yaw_variance='np.var' is not allowed; choose "
                                         r"one of \['circular', 'released'\]"):
        make_policy("coalign", yaw_variance="np.var")


def test_collaborator_without_a_landmark_path_keeps_its_pose_and_says_so():
    scene = sparse_scene()
    far = [scene.collab_boxes[0], scene.collab_boxes[1] + [500, 0, 0, 0, 0, 0, 0]]
    for mode in ("circular", "released"):
        result = coalign_align(scene.ego_boxes, scene.ego_unc, far, scene.collab_unc,
                               scene.reported, yaw_variance=mode)
        assert result.applied.tolist() == [True, False]
        assert result.reason == "slots [1]: no landmark path to the ego"
        assert np.array_equal(result.corrected[1], scene.reported[1])
