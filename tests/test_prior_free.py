"""Prior-free aligners (RANSAC, V2I-Calib(++), FreeAlign) and roco_fallback on constructed
scenes: large-offset recovery, periodic layouts, do-no-harm, parameters and helpers."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from roco_env.geometry import se2_apply
from roco_env.metrics import relative_pose_error
from roco_env.policies import make_policy
from roco_env.policies.fallback import roco_fallback_align
from roco_env.policies.freealign import common_subgraph, freealign_align
from roco_env.policies.prior_free import content_seed, fit_se2
from roco_env.policies.ransac import ransac_align
from roco_env.policies.roco import roco_align
from roco_env.policies.v2i_calib import sinkhorn, v2i_calib_align
from roco_env.testing.constructed_scenes import (
    make_scene,
    parking_rows,
    pose_error,
    random_objects,
    to_observation,
)

PRIOR_FREE = {
    "ransac": ransac_align,
    "v2i_calib": v2i_calib_align,
    "v2i_calib_oiou_hungarian": lambda *a, **k: v2i_calib_align(
        *a, metric="oiou", association="hungarian", **k),
    "freealign": freealign_align,
}
ALL = {**PRIOR_FREE, "roco_fallback": roco_fallback_align}
AGENTS = np.array([[0.0, 0.0, 0.0], [18.0, 6.0, 0.5], [-12.0, 14.0, -1.0]])


def sparse_scene(seed, translation=5.0, rotation_deg=10.0, noise=True):
    """12 cars spread over 80 m x 80 m, box noise 5 cm / 0.6 deg, both collaborators'
    reported poses off by ``translation`` m and ``rotation_deg`` deg."""
    rng = np.random.default_rng(seed)
    objects = random_objects(rng, 12, 40.0)
    errors = [pose_error(translation, rotation_deg, d) for d in rng.uniform(-np.pi, np.pi, 2)]
    return make_scene(objects, AGENTS, errors, noise=(0.05, 0.05, 0.01) if noise else None,
                      rng=rng)


def parking_scene(seed, translation):
    """Two jittered parking rows (2.5 m spacing) and nothing else; the collaborator's
    reported pose is ``translation`` m off along the rows."""
    rng = np.random.default_rng(seed)
    park = parking_rows(2, 14, origin=(-16, -3), occupancy=rng.random(28) < 0.85,
                        jitter=(0.05, 0.1, 2.0), rng=rng)
    agents = np.array([[-5.0, -12.0, 0.2], [6.0, 14.0, -2.5]])
    return make_scene(park, agents, [pose_error(translation, 0.5, 0.0)])


@pytest.mark.parametrize("name", sorted(ALL))
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_recovers_5m_10deg_offset_on_sparse_scene(name, seed):
    scene = sparse_scene(seed)
    result = ALL[name](*scene.args())
    assert result.applied.all(), result.reason
    err = relative_pose_error(result.corrected, scene.true)
    assert np.all(err[:, 0] < 0.15) and np.all(err[:, 1] < 0.3), err
    pairs = result.matched_pairs
    assert pairs.shape[0] >= 6 and set(pairs[:, 0]) <= {-1, 0, 1}


def test_roco_alone_cannot_recover_what_the_fallback_does():
    """Baseline for the test above: at 5 m / 10 deg RoCo keeps at least one prior."""
    scene = sparse_scene(0)
    assert not roco_align(*scene.args()).applied.all()


@pytest.mark.parametrize("name", sorted(ALL))
@pytest.mark.parametrize("translation", [0.6, 2.5, 5.0])
def test_parking_grid_is_left_alone_or_solved_never_made_worse(name, translation):
    for seed in range(3):
        scene = parking_scene(seed, translation)
        before = relative_pose_error(scene.reported, scene.true)[0]
        result = ALL[name](*scene.args())
        after = relative_pose_error(result.corrected, scene.true)[0]
        assert after[0] <= before[0] + 0.05 and after[1] <= before[1] + 0.1, (seed, result)
        if result.applied[0] and name in PRIOR_FREE:  # roco_fallback: roco's own choice
            assert after[0] < 0.3, result.reason


@pytest.mark.parametrize("name", sorted(PRIOR_FREE))
def test_do_no_harm_switch_applies_the_raw_estimate(name):
    """Periodic rows: do-no-harm keeps the prior where the layout is ambiguous;
    switched off, the raw estimate is applied whatever it is."""
    for seed in range(3):
        scene = parking_scene(seed, 2.5)
        kept = PRIOR_FREE[name](*scene.args())
        raw = PRIOR_FREE[name](*scene.args(), do_no_harm=False)
        assert raw.applied.all() and raw.reason == ""
        assert kept.applied[0] or "ambiguous" in kept.reason


@pytest.mark.parametrize("name", sorted(ALL))
def test_clean_poses_are_kept_or_refined_not_moved(name):
    scene = sparse_scene(3, translation=0.0, rotation_deg=0.0)
    result = ALL[name](*scene.args())
    err = relative_pose_error(result.corrected, scene.true)
    assert np.all(err[:, 0] < 0.1) and np.all(err[:, 1] < 0.2)


def test_roco_fallback_is_roco_when_roco_has_evidence():
    scene = sparse_scene(4, translation=0.8, rotation_deg=0.8)
    fallback, roco = roco_fallback_align(*scene.args()), roco_align(*scene.args())
    assert np.array_equal(fallback.corrected, roco.corrected)
    assert np.array_equal(fallback.applied, roco.applied)


@pytest.mark.parametrize("fallback", ["ransac", "v2i_calib", "freealign"])
def test_roco_fallback_reports_the_relocalised_slots(fallback):
    scene = sparse_scene(0)
    result = roco_fallback_align(*scene.args(), fallback=fallback, fallback_min_inliers=4)
    assert result.applied.all() and f"re-localised by {fallback}" in result.reason


def test_roco_fallback_replaces_a_wrong_large_roco_correction(monkeypatch):
    """A large correction RoCo applies itself is checked against the prior-free estimate
    (RoCo's first pass is replaced by one that moves slot 0 to a wrong pose 4 m away)."""
    import roco_env.policies.fallback as fallback

    scene = sparse_scene(8)
    calls = []

    def wrong_first_pass(*args, **kwargs):
        result = roco_align(*args, **kwargs)
        if not calls:
            result.corrected[0] = scene.true[0] + [4.0, 0.0, 0.0]
            result.applied[0] = True
        calls.append(result)
        return result

    monkeypatch.setattr(fallback, "roco_align", wrong_first_pass)
    unchecked = roco_fallback_align(*scene.args(), verify_beyond_m=None, verify_beyond_deg=None,
                                    refine_beyond_m=None, refine_beyond_deg=None)
    assert relative_pose_error(unchecked.corrected, scene.true)[0, 0] > 3.9
    calls.clear()
    checked = roco_fallback_align(*scene.args())
    assert len(calls) == 2 and "slots [0]: re-localised" in checked.reason
    assert np.all(relative_pose_error(checked.corrected, scene.true)[:, 0] < 0.15)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_roco_fallback_solves_a_far_correction_again_from_it(monkeypatch, seed):
    """A slot RoCo itself moves beyond refine_beyond_m / _deg is solved by RoCo once more
    with its own estimate as the prior (the first pass started metres away)."""
    import roco_env.policies.fallback as fallback

    scene = sparse_scene(seed, translation=2.5, rotation_deg=2.5)
    calls = []

    def recording(*args, **kwargs):
        calls.append((np.array(args[4]), roco_align(*args, **kwargs)))
        return calls[-1][1]

    monkeypatch.setattr(fallback, "roco_align", recording)
    once = roco_fallback_align(*scene.args(), refine_beyond_m=None, refine_beyond_deg=None)
    assert len(calls) == 1 and np.array_equal(once.corrected, calls[0][1].corrected)
    calls.clear()
    result = roco_fallback_align(*scene.args())
    (_, first), (prior, second) = calls
    moved = relative_pose_error(first.corrected, scene.reported)[:, 0] > 1.0
    assert moved.any() and "refined by roco from its own estimate" in result.reason
    np.testing.assert_array_equal(prior[moved], first.corrected[moved])
    np.testing.assert_array_equal(result.corrected[moved], second.corrected[moved])
    assert np.all(relative_pose_error(result.corrected, scene.true)[:, 0] < 0.15)


def test_policies_are_registered_and_act_in_the_ego_frame():
    scene = sparse_scene(5)
    obs = to_observation(scene, max_boxes=20, max_collaborators=4)
    for name in ("ransac", "v2i_calib", "freealign", "roco_fallback"):
        policy = make_policy(name)
        action = policy(obs)
        assert action.shape == (4, 3) and action.dtype == np.float32
        assert np.all(action[2:] == 0) and policy.last_result.applied[:2].all()


@pytest.mark.parametrize("name, params, field", [
    ("ransac", {"pair_tolerance": 0.0}, "pair_tolerance"),
    ("ransac", {"max_hypotheses": 0}, "max_hypotheses"),
    ("v2i_calib", {"metric": "iou"}, "metric"),
    ("v2i_calib", {"association": "greedy"}, "association"),
    ("freealign", {"min_subgraph": 1}, "min_subgraph"),
    ("freealign", {"edge_yaw_tolerance_deg": 90}, "edge_yaw_tolerance_deg"),
    ("ransac", {"ambiguity_ratio": 1.5}, "ambiguity_ratio"),
    ("ransac", {"inlier_distance": -1}, "inlier_distance"),
    ("roco_fallback", {"fallback": "magic"}, "fallback"),
    ("roco_fallback", {"fallback_nope": 1}, "nope"),
    ("roco_fallback", {"nope": 1}, "nope"),
    ("roco_fallback", {"verify_beyond_m": -1.0}, "verify_beyond_m"),
    ("roco_fallback", {"refine_beyond_deg": float("nan")}, "refine_beyond_deg"),
    ("v2i_calib", {"tau2": 1}, "tau2"),
])
def test_bad_parameters_name_the_field(name, params, field):
    with pytest.raises(ValueError, match=field):
        make_policy(name, **params)


def test_ransac_sampling_is_a_function_of_the_input():
    scene = sparse_scene(6)
    first = ransac_align(*scene.args(), max_hypotheses=5)
    second = ransac_align(*scene.args(), max_hypotheses=5)
    assert np.array_equal(first.corrected, second.corrected)
    assert content_seed(scene.ego_boxes) == content_seed(scene.ego_boxes.copy())
    assert content_seed(scene.ego_boxes) != content_seed(scene.ego_boxes[::-1])


finite = st.floats(-50, 50, allow_nan=False)


@settings(max_examples=60, deadline=None)
@given(x=finite, y=finite, yaw=st.floats(-3.1, 3.1), seed=st.integers(0, 1000),
       count=st.integers(2, 12))
def test_fit_se2_recovers_any_pose(x, y, yaw, seed, count):
    rng = np.random.default_rng(seed)
    src = rng.uniform(-30, 30, size=(count, 2))
    if np.ptp(src, axis=0).max() < 1.0:
        return
    pose = np.array([x, y, yaw])
    fitted = fit_se2(src, se2_apply(pose, src))
    assert np.allclose(se2_apply(fitted, src), se2_apply(pose, src), atol=1e-6)


@settings(max_examples=40, deadline=None)
@given(m=st.integers(1, 8), k=st.integers(1, 8), seed=st.integers(0, 1000))
def test_sinkhorn_plan_has_the_dustbin_marginals(m, k, seed):
    scores = np.random.default_rng(seed).normal(0, 3, size=(m, k))
    plan = np.exp(sinkhorn(scores, 0.5, 500))
    assert np.allclose(plan.sum(axis=0), np.r_[np.ones(k), m], rtol=1e-3, atol=1e-3)
    assert np.allclose(plan.sum(axis=1), np.r_[np.ones(m), k], rtol=1e-2, atol=1e-2)


def test_common_subgraph_finds_the_shared_nodes_and_rejects_the_rest():
    rng = np.random.default_rng(7)
    shared = rng.uniform(-30, 30, size=(8, 2))
    ego = np.vstack([shared, rng.uniform(-30, 30, size=(4, 2))])
    own = np.vstack([se2_apply(np.array([3.0, -2.0, 1.0]), shared)[::-1],
                     rng.uniform(-30, 30, size=(3, 2))])
    distance = lambda pts: np.hypot(*(pts[:, None] - pts[None, :]).transpose(2, 0, 1))  # noqa: E731
    nodes_e, nodes_o = common_subgraph(distance(ego), distance(own), (0, 7), 0.1)
    assert set(zip(nodes_e.tolist(), nodes_o.tolist(), strict=True)) == {
        (i, 7 - i) for i in range(8)}



def test_fallback_leaves_priors_roco_checked_and_reads_structured_reasons(monkeypatch):
    """Clean poses: RoCo keeps every prior by its significance test (slot_reasons say so),
    so the fallback never runs its prior-free aligner and returns RoCo's answer."""
    from roco_env.policies import fallback
    from roco_env.policies.roco import NOT_SIGNIFICANT

    scene = sparse_scene(0, translation=0.0, rotation_deg=0.0)
    first = roco_align(*scene.args())
    assert len(first.slot_reasons) == 2
    assert all(r.startswith(NOT_SIGNIFICANT) for r in first.slot_reasons)
    called = []
    monkeypatch.setitem(fallback.FALLBACKS, "ransac",
                        (lambda *a, **k: called.append(1), fallback.FALLBACKS["ransac"][1]))
    result = roco_fallback_align(*scene.args())
    assert not called
    assert result.slot_reasons == first.slot_reasons
