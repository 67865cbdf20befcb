"""RoCo as published: recovery, crowded matching vs CoAlign, ablation switches, do-no-harm."""

import dataclasses

import numpy as np
import pytest

from roco_env.geometry import se2_compose
from roco_env.metrics import matching_precision_recall, relative_pose_error
from roco_env.policies import make_policy
from roco_env.policies.base import AlignmentResult, apply_correction
from roco_env.policies.coalign import coalign_align
from roco_env.policies.matching import (
    MatchingParams,
    edge_consistency,
    match_star_graphs,
    pose_features,
)
from roco_env.policies.pose_kernels import GatedPairs, edge_similarity
from roco_env.policies.roco import roco_align
from roco_env.testing.constructed_scenes import (
    make_scene,
    parking_rows,
    pose_error,
    random_objects,
    to_observation,
)

AGENTS = np.array([[0.0, 0.0, 0.0], [15.0, 5.0, 0.5], [-10.0, 12.0, -1.0]])
ERRORS = np.array([pose_error(0.8, 0.8, 0.3), pose_error(0.8, -0.8, 2.0)])
PAIR = np.array([[0.0, 0.0, 0.0], [10.0, -8.0, 0.7]])


def sparse_scene(seed=1, count=12, **kwargs):
    objects = random_objects(np.random.default_rng(seed), count, 40.0)
    return make_scene(objects, AGENTS, ERRORS, **kwargs)


def parking_scene(seed):
    """Three rows of parked cars (2.5 m spacing, jittered like real parking, some reversed)
    plus scattered traffic; the collaborator's reported pose is 1.5 m off along the rows."""
    rng = np.random.default_rng(seed)
    park = parking_rows(
        3,
        12,
        origin=(-14, -7),
        occupancy=rng.random(36) < 0.8,
        jitter=(0.1, 0.3, 3.0),
        reversed_share=0.2,
        rng=rng,
    )
    others = random_objects(rng, 40, 60.0)
    gap = np.hypot(others[:, None, 0] - park[None, :, 0], others[:, None, 1] - park[None, :, 1])
    objects = np.vstack([park, others[gap.min(axis=1) > 8][:12]])
    agents = np.array([[-20.0, -20.0, 0.3], [20.0, 20.0, -2.0]])
    return make_scene(objects, agents, [pose_error(1.5, 0.8, 0.0)])


def errors(result, scene):
    return relative_pose_error(result.corrected, scene.true)


def test_recovers_large_pose_error_on_sparse_scene():
    scene = sparse_scene()
    result = roco_align(*scene.args())
    assert result.applied.all() and result.reason == ""
    err = errors(result, scene)
    assert np.all(err[:, 0] < 0.1) and np.all(err[:, 1] < 0.1)
    assert matching_precision_recall(result, *scene.padded_ids()) == (1.0, 1.0)
    assert result.outer_iterations >= 2 and result.solver_iterations > 0
    assert result.landmarks.shape[1] == 3


def test_joint_solve_every_round_agrees_with_default():
    scene = sparse_scene(noise=(0.05, 0.05, 0.01), rng=np.random.default_rng(3))
    fast = roco_align(*scene.args())
    joint = roco_align(*scene.args(), joint_every_round=True)
    assert np.allclose(fast.corrected, joint.corrected, atol=1e-3)


def test_crowded_parking_matching_beats_coalign_clustering():
    roco, global_leaves, coalign = [], [], []
    for seed in range(6):
        scene = parking_scene(seed)
        ids = scene.padded_ids()
        roco.append(matching_precision_recall(roco_align(*scene.args()), *ids)[0])
        wide = roco_align(*scene.args(), neighbor_radius=None)
        global_leaves.append(matching_precision_recall(wide, *ids))
        coalign_result = coalign_align(*scene.args())
        coalign.append(matching_precision_recall(coalign_result, *ids)[0])
        assert errors(wide, scene)[0, 0] < 0.1 and errors(coalign_result, scene)[0, 0] > 1.0
    assert np.mean(roco) > np.mean(coalign) + 0.2 and min(np.subtract(roco, coalign)) >= 0
    # star graphs spanning the whole scene see past the periodic rows: perfect matching
    assert np.all(np.array(global_leaves) == 1.0)
    assert np.mean(coalign) < 0.3


def test_edge_similarity_switch_matters_in_a_parking_lot():
    scene = parking_scene(0)
    with_edges = roco_align(*scene.args(), neighbor_radius=None)
    with_edges = matching_precision_recall(with_edges, *scene.padded_ids())[0]
    distance_only = roco_align(*scene.args(), use_edge_similarity=False)
    assert with_edges == 1.0
    # nearest-neighbour matching locks onto the neighbouring parking slot
    assert not matching_precision_recall(distance_only, *scene.padded_ids())[0] > 0.5


def test_iteration_switch_fixes_first_round_mismatches():
    scene = parking_scene(0)
    iterated = roco_align(*scene.args(), neighbor_radius=None)
    single = roco_align(*scene.args(), iterate=False, neighbor_radius=None)
    p_iter = matching_precision_recall(iterated, *scene.padded_ids())[0]
    p_single = matching_precision_recall(single, *scene.padded_ids())[0]
    assert single.outer_iterations == 1 < iterated.outer_iterations
    assert p_iter == 1.0 > p_single


def outlier_scene(seed):
    """The collaborator misplaces 3 of its ~10 boxes by 1.2 m: matched, but wrong."""
    rng = np.random.default_rng(seed)
    objects = random_objects(rng, 10, 30.0, min_gap=8)
    scene = make_scene(objects, PAIR, [pose_error(0.8, 0.8, 1.0)])
    boxes = scene.collab_boxes[0].copy()
    boxes[rng.choice(boxes.shape[0], 3, replace=False), :2] += [1.0, 0.6]
    return scene, (scene.ego_boxes, scene.ego_unc, [boxes], scene.collab_unc, scene.reported)


@pytest.mark.parametrize("seed", [0, 2])
def test_robust_kernel_switch_limits_outlier_damage(seed):
    scene, args = outlier_scene(seed)
    cauchy = errors(roco_align(*args), scene)[0]
    plain = errors(roco_align(*args, robust_kernel=None), scene)[0]
    huber = errors(roco_align(*args, robust_kernel="huber"), scene)[0]
    assert cauchy[0] < 0.1 and cauchy[0] < 0.5 * plain[0]
    assert huber[0] < plain[0]


def heading_noise_scene(seed, count=15, min_gap=8.0, yaw_noise_deg=8.0):
    rng = np.random.default_rng(seed)
    objects = random_objects(rng, count, 40.0, min_gap=min_gap)
    return make_scene(
        objects,
        PAIR,
        [pose_error(0.8, 0.8, 1.0)],
        noise=(0.05, 0.05, np.deg2rad(yaw_noise_deg)),
        rng=rng,
        sigma=(0.1, 0.1, 0.15),
    )


def test_distance_similarity_switch_rescues_noisy_headings():
    scene = heading_noise_scene(0)
    full = roco_align(*scene.args())
    edge_only = roco_align(*scene.args(), use_distance_similarity=False)
    assert full.applied.all() and errors(full, scene)[0, 0] < 0.1
    assert matching_precision_recall(full, *scene.padded_ids()) == (1.0, 1.0)
    # 8 deg heading noise makes far leaves inconsistent: S_edge alone falls below its bar
    # (tau1 / (1 + lam) = 0.25) for more than half of the true pairs
    assert matching_precision_recall(edge_only, *scene.padded_ids())[1] < 0.6


def test_neighbor_radius_switch_keeps_edges_local():
    """Heading noise rotates far leaves by metres: star graphs over every box dilute the
    edge consistency of true pairs, local star graphs (the default radius) keep it high
    (the parking lot shows where far leaves help)."""
    scene = heading_noise_scene(0, count=40, min_gap=5.0, yaw_noise_deg=2.0)
    own = scene.collab_boxes[0][:, [0, 1, 6]]
    landmarks = scene.ego_boxes[:, [0, 1, 6]]
    medians = []
    for radius in (None, 12.0):
        params = MatchingParams(tau1=0.0, use_distance_similarity=False, neighbor_radius=radius)
        land, box, edge = match_star_graphs(
            landmarks, own, se2_compose(scene.true[0], own), params
        )
        true_pair = scene.ego_ids[land] == scene.collab_ids[0][box]
        assert true_pair.all()
        medians.append(np.median(edge))
    assert medians[1] > medians[0] + 0.2
    local = roco_align(*scene.args(), use_distance_similarity=False, neighbor_radius=12.0)
    assert local.applied.all() and errors(local, scene)[0, 0] < 0.1


def test_do_no_harm_keeps_prior_on_weak_evidence():
    objects = np.array([[5, 0, 0.8, 4.5, 1.9, 1.6, 0.1], [12, 6, 0.8, 4.5, 1.9, 1.6, 1.0]])
    scene = make_scene(objects, PAIR, [pose_error(0.8, 0.8, 1.0)])
    result = roco_align(*scene.args())
    assert not result.applied.any() and "min_matches=3" in result.reason
    assert np.array_equal(result.corrected, scene.reported)
    assert roco_align(*scene.args(), min_matches=2).applied.all()


# Realistic-detector box noise (sigma_xy 0.06 m + 0.002 m/m at ~30 m, yaw ~1.7 deg),
# reported honestly: the boxes carry the sigma their noise is drawn with.
CALIBRATED = (0.12, 0.12, 0.03)


def calibrated_scene(seed, error):
    rng = np.random.default_rng(seed)
    objects = random_objects(rng, 12, 30.0, min_gap=8.0)
    return make_scene(objects, PAIR, [error], sigma=CALIBRATED, noise=CALIBRATED, rng=rng)


def test_significance_test_keeps_clean_poses_and_corrects_real_offsets():
    """Clean reported poses: the estimate differs from them only by estimation noise, so
    the chi2(3) test at 0.99 keeps the prior on ~99% of frames (without it, every frame
    is 'corrected' by the noise). A 0.3 m / 0.3 deg offset is found and corrected."""
    kept = 0
    for seed in range(40):
        scene = calibrated_scene(seed, np.zeros(3))
        result = roco_align(*scene.args())
        if not result.applied[0]:
            kept += 1
            assert "correction not significant" in result.reason
            assert np.array_equal(result.corrected, scene.reported)
    assert kept >= 36
    clean = calibrated_scene(0, np.zeros(3))
    assert roco_align(*clean.args(), significance=None).applied.all()  # the old rule
    assert roco_align(*clean.args(), significance=0).applied.all()
    for seed in range(20):
        scene = calibrated_scene(seed, pose_error(0.3, 0.3, 1.0))
        result = roco_align(*scene.args())
        assert result.applied.all() and result.reason == ""
        err = errors(result, scene)[0]
        assert err[0] < 0.2 and err[1] < 0.3  # from ~0.3 m / 0.3 deg to the noise floor


def uneven_scene(seed, error):
    """Twelve cars seen by an ego whose headings are poor and say so (yaw noise 0.08 rad,
    sigma 0.1 rad: an RSU's diagonal view of the crossing) and by a collaborator that sees
    them along its axes (noise 0.003 rad, sigma 0.004 rad), centres as calibrated_scene's."""
    rng = np.random.default_rng(seed)
    objects = random_objects(rng, 12, 30.0, min_gap=8.0)
    scene = make_scene(objects, PAIR, [error], sigma=(0.12, 0.12, 0.004),
                       noise=(0.1, 0.1, 0.003), rng=rng)
    ego_boxes, ego_unc = scene.ego_boxes.copy(), scene.ego_unc.copy()
    ego_boxes[:, 6] += rng.normal(0.0, 0.08, ego_boxes.shape[0])
    ego_unc[:, 2] = 0.1
    return dataclasses.replace(scene, ego_boxes=ego_boxes, ego_unc=ego_unc)


def test_round_edges_carry_the_landmarks_uncertainty():
    """A collaborator's box against a landmark held fixed at the ego's box differs by both
    boxes' errors. Weighed by the collaborator's yaw sigma alone, the ego's 5-degree heading
    errors make most true matches outliers and the inlier test keeps a 0.4 m / 0.4 deg
    error; weighed by the difference's covariance they correct it. Clean poses stay kept."""
    for seed in range(10):
        scene = uneven_scene(seed, pose_error(0.4, 0.4, 1.0))
        result = roco_align(*scene.args())
        assert result.applied.all() and result.reason == ""
        err = errors(result, scene)[0]
        assert err[0] < 0.15 and err[1] < 0.2
    box_rule = [roco_align(*uneven_scene(seed, pose_error(0.4, 0.4, 1.0)).args(),
                           round_information="box") for seed in range(10)]
    assert sum("inlier matches < min_matches" in r.reason for r in box_rule) >= 6
    for seed in range(20):
        assert not roco_align(*uneven_scene(seed, np.zeros(3)).args()).applied.any()


def test_collaborator_linked_only_through_another_is_retried():
    rng = np.random.default_rng(2)
    near = random_objects(rng, 8, 15.0)
    far = random_objects(rng, 8, 15.0) + [90.0, 0, 0, 0, 0, 0, 0]
    agents = np.array([[0.0, 0.0, 0.0], [110.0, 5.0, 2.5], [60.0, -3.0, 0.2]])
    errs = np.array([pose_error(0.8, 0.8, 1.0), pose_error(0.8, -0.8, -1.0)])
    scene = make_scene(np.vstack([near, far]), agents, errs, sensor_range=65.0)
    result = roco_align(*scene.args())
    assert result.applied.all()  # slot 0 sees only `far`, linked via slot 1
    # slot 0 is 110 m away and constrained through slot 1: the priors weigh a little more
    assert np.all(errors(result, scene)[:, 0] < 0.15)
    assert roco_align(*scene.args(), prior_sigma_t=10.0, prior_sigma_r_deg=10.0).applied.all()


def test_policy_maps_observation_to_action():
    scene = sparse_scene()
    obs = to_observation(scene, max_boxes=20, max_collaborators=3)
    policy = make_policy("roco", tau2=2.5)
    action = policy(obs)
    assert action.shape == (3, 3) and action.dtype == np.float32 and np.all(action[2] == 0)
    corrected = apply_correction(obs["collab_rel_poses"], action)[:2]
    assert np.all(relative_pose_error(corrected, scene.true)[:, 0] < 0.1)
    assert isinstance(policy.last_result, AlignmentResult)
    assert policy.last_result.applied.tolist() == [True, True, False]


def test_matching_scores_and_assignment():
    assert edge_consistency(np.array([1.0, 2.0, 0.3]), np.array([1.0, 2.0, 0.3])) == 1.0
    # a 1 m translation difference with equal yaw: exp(-1)
    assert np.isclose(edge_consistency(np.array([1.0, 0, 0]), np.array([0.0, 0, 0])), np.exp(-1))
    lands = np.array([[0.0, 0, 0], [10.0, 0, 0], [0.0, 10, 0]])
    boxes = lands[[2, 0, 1]] + [0.4, 0.0, 0.0]
    land, box, score = match_star_graphs(lands, boxes, boxes, MatchingParams())
    assert land.tolist() == [0, 1, 2] and box.tolist() == [1, 2, 0]
    assert np.allclose(score, 1.0 + np.exp(-0.4))
    assert (
        match_star_graphs(lands, boxes + [5.0, 0, 0], boxes + [5.0, 0, 0], MatchingParams())[0].size
        == 0
    )  # nothing within tau2


@pytest.mark.parametrize("radius", [None, 15.0])
def test_vectorised_edge_similarity_matches_the_definition(radius):
    rng = np.random.default_rng(5)
    lands = np.column_stack([rng.uniform(-30, 30, (25, 2)), rng.uniform(-3, 3, 25)])
    own = np.column_stack([rng.uniform(-30, 30, (20, 2)), rng.uniform(-3, 3, 20)])
    ego = own + [0.5, -0.3, 0.0]
    params = MatchingParams(tau2=12.0, neighbor_radius=radius)
    dis = np.hypot(lands[:, None, 0] - ego[None, :, 0], lands[:, None, 1] - ego[None, :, 1])
    gated = dis <= params.tau2
    cand_p, cand_q = np.nonzero(gated)
    leaves = np.nonzero(gated.any(axis=1))[0]  # landmarks m with an initial match
    partner = np.argmin(np.where(gated[leaves], dis[leaves], np.inf), axis=1)  # n = A(m)
    pairs = GatedPairs(cand_p, cand_q, dis[gated], leaves, partner)
    fast = edge_similarity(pose_features(lands), pose_features(own), pairs,
                           -1.0 if radius is None else radius**2)

    def rel(a, b):  # pose of b in the frame of a
        c, s = np.cos(a[2]), np.sin(a[2])
        d = b[:2] - a[:2]
        return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], b[2] - a[2]])

    for k, (p, q) in enumerate(zip(cand_p, cand_q, strict=True)):
        scores = []
        for m in range(len(lands)):
            if m == p or not gated[m].any():
                continue
            n = np.argmin(np.where(gated[m], dis[m], np.inf))  # initial match A(m)
            near = radius is None or (
                np.hypot(*(lands[m, :2] - lands[p, :2])) <= radius
                and np.hypot(*(own[n, :2] - own[q, :2])) <= radius
            )
            if n != q and near:
                scores.append(edge_consistency(rel(lands[p], lands[m]), rel(own[q], own[n])))
        assert np.isclose(fast[k], np.mean(scores) if scores else 0.0, atol=1e-9)


def test_matching_precision_recall_definitions():
    result = AlignmentResult(
        np.zeros((2, 3)),
        np.ones(2, bool),
        matched_pairs=np.array([[-1, 0, 0, 1], [-1, 1, 0, 0], [0, 2, 1, 0]]),
    )
    ego_ids = np.array([7, 8, -1])
    collab_ids = np.array([[8, 7, 9], [9, -1, -1]])
    precision, recall = matching_precision_recall(result, ego_ids, collab_ids)
    # pairs: (7,7) ok, (8,8) ok, (9,9) collab<->collab ok; truths: 7, 8, 9 -> all found
    assert precision == 1.0 and recall == 1.0
    wrong = AlignmentResult(
        np.zeros((2, 3)), np.ones(2, bool), matched_pairs=np.array([[-1, 0, 0, 0]])
    )
    assert matching_precision_recall(wrong, ego_ids, collab_ids) == (0.0, 0.0)
    assert matching_precision_recall(result, ego_ids, collab_ids, include_collab_pairs=False) == (
        1.0,
        1.0,
    )
    empty = AlignmentResult(np.zeros((2, 3)), np.zeros(2, bool))
    p, r = matching_precision_recall(empty, ego_ids, collab_ids)
    assert np.isnan(p) and r == 0.0
    with pytest.raises(ValueError, match="matched_pairs"):
        matching_precision_recall(result, ego_ids, collab_ids[:1])


def test_bad_parameters_raise():
    scene = sparse_scene()
    for bad in (
        {"tau2": 0.0},
        {"robust_kernel": "tukey"},
        {"min_matches": 0},
        {"significance": 1.0},
        {"significance": -0.5},
        {"round_information": "landmark"},
        {"round_information": "difference", "joint_every_round": True},
        {"use_edge_similarity": False, "use_distance_similarity": False},
    ):
        with pytest.raises(ValueError, match=next(iter(bad))):
            roco_align(*scene.args(), **bad)
    with pytest.raises(ValueError, match="unknown roco parameter"):
        make_policy("roco", tau3=1.0)


def test_coarse_gate_catches_errors_beyond_tau2():
    objects = random_objects(np.random.default_rng(4), 12, 35.0, min_gap=8.0)
    scene = make_scene(objects, PAIR, [pose_error(3.6, 0.8, 0.5)])
    recovered = roco_align(*scene.args())
    single_gate = roco_align(*scene.args(), coarse_tau2=None)
    assert recovered.applied.all() and errors(recovered, scene)[0, 0] < 0.1
    assert not single_gate.applied.any()
