"""roco_antialias: aliasing in repetitive layouts is resolved or left alone, every switch
matters on a scene built to need it, tracks are per (ego, collaborator), degenerate inputs."""

from dataclasses import replace

import numpy as np
import pytest

from roco_env.policies import make_policy
from roco_env.policies.ambiguity import Ambiguity
from roco_env.policies.antialias import THIN_FIT_T, _thin, antialias_align
from roco_env.policies.base import apply_correction
from roco_env.policies.hypotheses import translation_peaks
from roco_env.policies.roco import roco_align
from roco_env.testing.constructed_scenes import (
    make_scene,
    parking_rows,
    pose_error,
    random_objects,
    to_observation,
)

ROW_CAR = np.array([0.0, 0.0, 0.8, 4.5, 1.9, 1.6, 0.0])


def error_m(corrected, scene) -> float:
    return float(np.hypot(*(corrected[0, :2] - scene.true[0, :2])))


def without_self(scene):
    """Nobody detects its own vehicle: drop each agent's box at its own origin."""

    def keep(boxes):
        return np.hypot(boxes[:, 0], boxes[:, 1]) > 0.5

    ego, collab = keep(scene.ego_boxes), keep(scene.collab_boxes[0])
    return replace(
        scene,
        ego_boxes=scene.ego_boxes[ego],
        ego_unc=scene.ego_unc[ego],
        ego_ids=scene.ego_ids[ego],
        collab_boxes=[scene.collab_boxes[0][collab]],
        collab_unc=[scene.collab_unc[0][collab]],
        collab_ids=[scene.collab_ids[0][collab]],
    )


def lot(
    seed,
    error_x=-1.4,
    rows=2,
    per_row=60,
    origin=-75.0,
    size_jitter=0.0,
    place_jitter=(0.0, 0.0, 0.0),
    collab_x=15.0,
    ego_x=0.0,
    cars_at_agents=False,
    sensor_range=30.0,
):
    """Rows of parked cars 2.5 m apart (rows 7 m apart, aisles at y = 3.5 + 7 k), the ego and
    one collaborator in the first aisle, the collaborator reported ``error_x`` m off along
    the rows (so nearer the one-stall alias than the truth when |error_x| > 1.25)."""
    rng = np.random.default_rng(seed)
    objects = parking_rows(
        rows, per_row, origin=(origin, 0.0), jitter=place_jitter, rng=rng
    )
    objects[:, 3:6] *= np.exp(rng.normal(0.0, size_jitter, (objects.shape[0], 3)))
    agents = np.array([[ego_x, 3.5, 0.0], [collab_x, 3.5, 0.0]])
    if cars_at_agents:
        cars = np.tile(ROW_CAR, (2, 1))
        cars[:, [0, 1, 6]] = agents
        objects = np.vstack([objects, cars])
    direction = 0.0 if error_x > 0 else np.pi
    error = pose_error(abs(error_x), 0.3, direction)
    scene = make_scene(
        objects, agents, [error], sensor_range=sensor_range, noise=(0.05, 0.05, 0.01), rng=rng
    )
    return without_self(scene) if cars_at_agents else scene


@pytest.mark.parametrize("error_x", [-2.0, -1.4, 1.6, 2.4, 3.0])
def test_one_stall_shift_is_resolved_where_roco_aliases(error_x):
    """Finite rows of cars of varied sizes: RoCo locks onto a neighbouring stall, the
    hypotheses find the truth; never worse than the reported pose."""
    scene = lot(0, error_x, rows=3, per_row=16, origin=-18.0, size_jitter=0.06,
                place_jitter=(0.05, 0.05, 1.0), collab_x=12.0, sensor_range=70.0)
    reported = error_m(scene.reported, scene)
    result, decisions = antialias_align(*scene.args())
    assert error_m(result.corrected, scene) < 0.1
    assert decisions[0].pose is not None and decisions[0].margin >= 20.0
    assert error_m(roco_align(*scene.args()).corrected, scene) > 2.0 - 0.5 * (reported < 2.5)


@pytest.mark.parametrize("seed", range(3))
def test_ambiguous_lot_keeps_the_reported_pose_along_the_rows(seed):
    """Identical cars, no jitter, rows longer than the sensors: every stall shift explains the
    boxes equally well, so the pose keeps the reported x (along the rows) and takes at most
    the y and yaw the rows determine (never made worse); without the ambiguity diagnosis
    the reported pose is kept in full."""
    scene = lot(seed)
    result, decisions = antialias_align(*scene.args())
    assert decisions[0].pose is None and decisions[0].margin < 20.0
    ambiguity = decisions[0].ambiguity
    assert ambiguity.determined == 2 and abs(ambiguity.undetermined[0, 0]) > 0.99
    assert result.corrected[0, 0] == pytest.approx(scene.reported[0, 0], abs=0.01)
    assert error_m(result.corrected, scene) <= error_m(scene.reported, scene) + 0.01
    kept, decisions = antialias_align(*scene.args(), use_ambiguity=False)
    assert decisions[0].pose is None and not kept.applied[0]
    np.testing.assert_allclose(kept.corrected, scene.reported)


# Each cue decides a scene built without the others: a lot whose one-stall shifts only
# that cue tells apart. With the cue on, the shift is resolved; with it off, no hypothesis
# wins the margin and RoCo alone lands one stall (1.4 m) off.
#  - size: cars of varied sizes;
#  - mutual detection: identical cars, the ego and the collaborator are cars in the aisle,
#    each seen only by the other;
#  - free space: identical cars, the collaborator near the end of the rows reported towards
#    their interior; only free space notices the ego's end-of-row cars it should see.
CUE_SCENES = {
    "use_size": {"size_jitter": 0.06},
    "use_mutual_detection": {"cars_at_agents": True},
    "use_free_space": {"rows": 4, "per_row": 20, "origin": 0.0, "ego_x": 25.0,
                       "collab_x": 40.0},
}


@pytest.mark.parametrize("switch", list(CUE_SCENES))
def test_each_cue_switch_decides_the_scene_built_to_need_it(switch):
    scene = lot(1, **CUE_SCENES[switch])
    on, _ = antialias_align(*scene.args())
    off, decisions = antialias_align(*scene.args(), **{switch: False})
    assert error_m(on.corrected, scene) < 0.1
    assert decisions[0].pose is None
    assert error_m(off.corrected, scene) == pytest.approx(1.4, abs=0.05)


def test_track_switch_carries_an_earlier_decision():
    scene = lot(1)
    track = [(scene.true[0], 1.0)]
    on, _ = antialias_align(*scene.args(), tracks=track)
    off, _ = antialias_align(*scene.args(), tracks=track, use_track=False)
    assert error_m(on.corrected, scene) < 0.1
    assert error_m(off.corrected, scene) == pytest.approx(1.4, abs=0.05)


def test_track_overruled_by_the_evidence_is_dropped():
    """A track predicting the alias two stalls over (its prior, 100 chi2 units at age 1,
    outweighs the evidence's preference for the truth): the evidence beats the track's pick
    by more than min_margin, so the track is dropped and the decision taken without it."""
    scene = lot(0, -0.6, rows=3, per_row=16, origin=-18.0, size_jitter=0.02,
                place_jitter=(0.05, 0.05, 0.017), collab_x=12.0, sensor_range=70.0)
    alias = scene.true[0] + np.array([5.0, 0.0, 0.0])
    result, decisions = antialias_align(*scene.args(), tracks=[(alias, 1.0)])
    assert decisions[0].track_dropped and decisions[0].pose is not None
    assert error_m(result.corrected, scene) < 0.1
    kept, decisions = antialias_align(*scene.args(), tracks=[(scene.true[0], 1.0)])
    assert not decisions[0].track_dropped and error_m(kept.corrected, scene) < 0.1


def scatter(seed, error):
    """80 cars scattered over 80 m (5 m apart at least, seeded by ``seed``), the ego at the
    origin and one collaborator at (10, 5) m reported ``error`` (3,) off, 70 m range."""
    rng = np.random.default_rng(seed)
    objects = random_objects(rng, 80, 80.0, min_gap=5.0)
    return make_scene(objects, np.array([[0.0, 0.0, 0.0], [10.0, 5.0, 0.5]]), [error],
                      sensor_range=70.0, noise=(0.05, 0.05, 0.01), rng=rng)


def test_roco_correction_without_hypotheses_that_its_boxes_support_is_applied():
    """A scatter of cars, the collaborator reported 9.5 m / 5 deg off: nothing refines within
    the 7 m search (in this direction not even from the vote at the reported rotation),
    RoCo's matching finds the truth itself, which explains the collaborator's boxes far
    better than the reported pose, so the correction stands (keeping the reported pose
    whenever a pose beyond the search explains the boxes better than the reported one cost
    v2x_crossroad at 5 m/deg such corrections)."""
    scene = scatter(3, pose_error(9.5, 5.0, 2.5))
    result, decisions = antialias_align(*scene.args())
    assert decisions[0].hypotheses == 0 and decisions[0].support >= 20.0
    assert result.applied[0] and error_m(result.corrected, scene) < 0.1


# The stress search's highway (roco-env stress --policy roco_antialias --objective harm
# --budget 150 --seeds 0 1 --steps 4, trial 86): at seed 1 RoCo moved a collaborator that
# shares no box with the ego (11 m off, no hypothesis) 1 m further through the other
# collaborators' boxes; its boxes score -50 chi2 units at RoCo's pose as at the reported
# one (177 at the truth; the poses the search beyond finds near it score 145-175).
FOUND_HIGHWAY = {
    "traffic.layout": "highway", "fill": 0.7217615179391893,
    "traffic.min_gap": 0.8953161554528913, "agents.cavs": 4, "agents.rsus": 0,
    "agents.comm_range": 47.50557790690607, "noise.model": "laplace",
    "noise.sigma_t": 2.9309470348927054, "noise.sigma_r": 0.2444223667925808,
}


def slot_records(tmp_path, params: dict, seed: int):
    """roco_antialias on the stress space's scene ``params`` (reset seed ``seed``, 4 steps):
    (Decision, applied, reason) of every filled slot of every call, and the episode's
    samples."""
    from roco_env.policies.antialias import AntiAliasPolicy
    from roco_env.scenario import save_scenario
    from roco_env.stress.space import load_space, scenario_for
    from roco_env.sweeps.cells import Cell
    from roco_env.sweeps.episode import run_episode

    path = save_scenario(scenario_for(load_space(None), params, "found"), tmp_path / "found.yaml")
    records = []

    class Recording(AntiAliasPolicy):
        def align_view(self, view, observation, info):
            result = super().align_view(view, observation, info)
            records.extend(zip(self.last_decisions, result.applied, result.slot_reasons,
                               strict=True))
            return result

    _, samples = run_episode(Cell(str(path), None, "roco_antialias", seed, 4),
                             policy_factory=Recording)
    return records, samples


def kept_corrections(tmp_path, params: dict, seed: int):
    """:func:`slot_records`' (hypotheses, reason) of the slots whose correction was not
    applied for want of support (Decision.support below min_margin), and the samples."""
    records, samples = slot_records(tmp_path, params, seed)
    return [(d.hypotheses, r) for d, applied, r in records
            if d.support < 20.0 and not applied], samples


def test_roco_correction_without_hypotheses_that_its_boxes_do_not_support_is_not_applied(
        tmp_path):
    """On the found highway the collaborator RoCo moved through the others' boxes keeps its
    reported pose (Decision.support below min_margin, the slot's reason) and no pose is made
    worse."""
    from roco_env.metrics import harm_share

    kept, samples = kept_corrections(tmp_path, FOUND_HIGHWAY, 1)
    assert any(h == 0 for h, _ in kept)
    assert all("better than the reported pose (< 20), reported pose kept" in r
               for h, r in kept if h == 0)
    assert harm_share(samples["before"], samples["after"]) == 0.0


# The stress search's RSU pair (roco-env stress --policy roco_antialias --objective harm
# --budget 150 --seeds 0 1 --steps 4 --seed 2, trial 33): two RSUs ~120 m apart share 3 boxes
# ~60 m from both; at seed 0 RoCo moved one, reported 0.19 m off, to 0.70 m off (Wald 20 >
# 11.3, a significant correction by the boxes' covariances), a move its hypothesis' pairs
# support by 15.8 chi2 units only.
FOUND_RSU_PAIR = {
    "traffic.layout": "highway", "fill": 0.20434857980129478,
    "traffic.min_gap": 3.0067103718494166, "agents.cavs": 2, "agents.rsus": 2,
    "agents.comm_range": 121.925801881849, "noise.model": "gaussian",
    "noise.sigma_t": 0.20057219337520435, "noise.sigma_r": 0.3902021437138314,
}


# The stress search's packed jam (the same command, --seed 7, trial 9, against the aligner
# with the rule above): at seed 1 an ambiguous collaborator (reported 0.14 m off) took its
# determined part 0.59 m, significant by its pairs' Wald test but worth 7.5 of their
# information, and ended 0.71 m off.
FOUND_JAM = {
    "traffic.layout": "traffic_jam", "fill": 0.9933019472553762,
    "traffic.min_gap": 0.9664116666153992, "agents.cavs": 2, "agents.rsus": 2,
    "agents.comm_range": 141.19355253240678, "noise.model": "ar1",
    "noise.sigma_t": 0.10846950742421183, "noise.sigma_r": 0.2518715254853959,
}


def test_a_thin_fit_its_pairs_do_not_support_is_not_applied_on_the_found_rsu_pair(tmp_path):
    """On the found RSU pair a trusted pick's correction that its thin fit's pairs do not
    support by min_margin is not applied (the slot's reason says so) and no pose is made
    worse (2.08% of the poses without the rule)."""
    from roco_env.metrics import harm_share

    records, samples = slot_records(tmp_path, FOUND_RSU_PAIR, 0)
    kept = [r for _, _, r in records if "RoCo's correction is worth only" in r]
    assert kept and all("information (< 20)" in r for r in kept)
    assert harm_share(samples["before"], samples["after"]) == 0.0


def test_the_found_jam_makes_no_pose_worse(tmp_path):
    """The found jam (1.04% of its poses made worse without the thin-fit rule) makes none
    worse. Whether its borderline episode reaches the rule at all depends on the CPU's
    rounding (a found scene is borderline by construction: a Wald statistic of 11.33
    against 11.34 on one machine); the constructed thin row below pins the rule."""
    from roco_env.metrics import harm_share

    _, samples = slot_records(tmp_path, FOUND_JAM, 1)
    assert harm_share(samples["before"], samples["after"]) == 0.0


@pytest.mark.parametrize("seed", [0, 1])
def test_a_thin_determined_part_its_pairs_do_not_support_is_not_applied(seed):
    """One row of identical cars, the collaborator 50 m from the ego with 30 m sensors (the
    two share the 10 m between them), reported 0.7 m across the row and 0.8 deg off: the
    row leaves the along-row shift undetermined, and the determined part (across, yaw) is
    significant but its few, far pairs pin the origin thinly and support the move by less
    than min_margin (11.2 and 14.5), so the reported pose is kept in full."""
    rng = np.random.default_rng(seed)
    objects = parking_rows(1, 40, origin=(-40.0, 0.0), rng=rng)
    agents = np.array([[0.0, 3.5, 0.0], [50.0, 3.5, 0.0]])
    scene = make_scene(objects, agents, [pose_error(0.7, 0.8, np.pi / 2)], sensor_range=30.0,
                       noise=(0.05, 0.05, 0.01), rng=rng)
    result, decisions = antialias_align(*scene.args())
    reason = result.slot_reasons[0]
    assert "the determined part is worth only" in reason and "information (< 20)" in reason
    assert decisions[0].ambiguity.determined == 2 and not result.applied[0]
    np.testing.assert_allclose(result.corrected, scene.reported)


def test_correction_of_a_fit_that_is_not_thin_is_applied():
    """A scatter of cars, the collaborator reported 1.5 m / 1 deg off: the trusted pick's
    pairs pin its origin to well under THIN_FIT_T, so its correction is not asked for its
    worth (support NaN) and stands."""
    scene = scatter(1, pose_error(1.5, 1.0, 2.0))
    result, decisions = antialias_align(*scene.args())
    assert decisions[0].ambiguity.translation_std < THIN_FIT_T
    assert decisions[0].pose is not None and np.isnan(decisions[0].support)
    assert result.applied[0] and error_m(result.corrected, scene) < 0.1


def shifted_pattern(error, seed=0):
    """Identical cars in two lanes, seen in part by each agent (the rest hidden, as in a
    jam): the ego sees cars at x = 10, 15 (lane y = 0) and 21, 26 (lane y = 4), the
    collaborator (8 m from the ego) at 15, 20 and 26, 31. At the truth they share 2 boxes
    (too few to refine into a hypothesis); 5 m along the lanes the collaborator's four boxes
    fall on the ego's four (the alias, the only hypothesis). The collaborator is reported
    ``error`` (3,) off."""
    ego_xy = np.array([[10.0, 0.0], [15.0, 0.0], [21.0, 4.0], [26.0, 4.0]])
    collab_xy = np.array([[15.0, 0.0], [20.0, 0.0], [26.0, 4.0], [31.0, 4.0]])
    world = np.unique(np.vstack([ego_xy, collab_xy]), axis=0)
    objects = np.tile(ROW_CAR, (world.shape[0], 1))
    objects[:, :2] = world
    scene = make_scene(objects, np.array([[16.0, -6.0, 0.0], [24.0, -6.0, 0.0]]),
                       [np.asarray(error, dtype=float)], sensor_range=60.0,
                       noise=(0.05, 0.05, 0.01), rng=np.random.default_rng(seed))

    def seen(ids, xy):
        return (np.hypot(*(world[ids][:, None] - xy[None]).transpose(2, 0, 1)) < 1e-9).any(1)

    ego, collab = seen(scene.ego_ids, ego_xy), seen(scene.collab_ids[0], collab_xy)
    return replace(
        scene, ego_boxes=scene.ego_boxes[ego], ego_unc=scene.ego_unc[ego],
        ego_ids=scene.ego_ids[ego], collab_boxes=[scene.collab_boxes[0][collab]],
        collab_unc=[scene.collab_unc[0][collab]], collab_ids=[scene.collab_ids[0][collab]])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_far_pick_that_the_reported_pose_explains_nearly_as_well_is_not_trusted(seed):
    """The stress search's packed-row aliases, constructed (shifted_pattern): reported 0.3 m
    off, the only hypothesis is the alias 5 m along the lanes (4 pairs, 25 chi2 units of
    prior for the move), which beats no distinct hypothesis (margin about 80) and was
    applied (5 m off). The reported pose refined with its own 2 pairs scores within
    min_margin of it, priors counted: the pick is not trusted and the reported pose is
    kept."""
    scene = shifted_pattern([0.3, 0.0, 0.0], seed)
    old, old_decisions = antialias_align(*scene.args(), use_ambiguity=False)
    assert old_decisions[0].hypotheses == 1 and old_decisions[0].margin >= 20.0
    assert abs(error_m(old.corrected, scene) - 5.0) < 0.2
    result, decisions = antialias_align(*scene.args())
    assert decisions[0].pose is None and decisions[0].margin < 20.0
    assert decisions[0].ambiguity.determined == 3
    np.testing.assert_array_equal(result.corrected[0], scene.reported[0])
    assert result.slot_reasons[0].startswith("ambiguous (margin")
    again, repeated = antialias_align(*scene.args())
    np.testing.assert_array_equal(again.corrected, result.corrected)
    assert repeated[0].margin == decisions[0].margin


def test_far_pick_that_explains_the_boxes_far_better_than_the_reported_pose_is_applied():
    """A scatter of cars, the collaborator reported 3 m / 2 deg off: the pick is distinct
    from the reported pose, which explains the boxes far worse even with the move's prior
    counted, so the pick stays trusted and the truth is found."""
    scene = scatter(2, pose_error(3.0, 2.0, 2.0))
    result, decisions = antialias_align(*scene.args())
    assert np.hypot(*(decisions[0].pose[:2] - scene.reported[0, :2])) > 2.5
    assert decisions[0].margin >= 20.0 and result.applied[0]
    assert error_m(result.corrected, scene) < 0.1


# The stress search's highway (the same command, --seed 4, trial 80, against commit
# 470b818): two RSUs 118 m apart, cars heading along the road; at seed 1 the rotation vote
# landed 5 deg from the truth, every peak at that rotation refined to aliases 5.4-6 m along
# the road, and the one picked moved a pose reported 2.1 m off to 5.6 m off (the truth, seeded
# by hand, explains the boxes 100 chi2 units better).
FOUND_RSU_HIGHWAY = {
    "traffic.layout": "highway", "fill": 0.8958834255516935,
    "traffic.min_gap": 1.0944941904168957, "agents.cavs": 3, "agents.rsus": 2,
    "agents.comm_range": 148.09038761991474, "noise.model": "ar1",
    "noise.sigma_t": 0.8582050748665334, "noise.sigma_r": 1.766889075550431,
}


def peaks_at_the_reported_rotation(monkeypatch) -> list:
    """Record every call of the extra vote at the reported rotation (its ``rotated`` pose)."""
    from roco_env.policies import antialias

    calls = []

    def spy(ego, collab, rotated, p, most=None):
        calls.append(np.array(rotated))
        return translation_peaks(ego, collab, rotated, p, most)

    monkeypatch.setattr(antialias, "translation_peaks", spy)
    return calls


def test_rotation_vote_far_from_the_reported_rotation_adds_a_peak_at_it(tmp_path, monkeypatch):
    """On the found RSU highway the rotation vote lands more than distinct_r_deg from the
    reported rotation: one more peak is voted at the reported rotation, it refines to the
    truth, and no pose is made worse (2.5% of the poses at this seed without it); the
    episode repeats exactly."""
    from roco_env.metrics import harm_share

    calls = peaks_at_the_reported_rotation(monkeypatch)
    _, samples = slot_records(tmp_path, FOUND_RSU_HIGHWAY, 1)
    assert calls
    assert harm_share(samples["before"], samples["after"]) == 0.0
    _, again = slot_records(tmp_path, FOUND_RSU_HIGHWAY, 1)  # deterministic
    np.testing.assert_array_equal(np.asarray(again["after"]), np.asarray(samples["after"]))


def test_rotation_vote_near_the_reported_rotation_adds_no_peak(monkeypatch):
    """A scatter of cars, the collaborator reported 1.5 m / 1 deg off: the rotation vote
    lands within distinct_r_deg of the truth, hence of the reported rotation too, and
    no vote at the reported rotation is added."""
    calls = peaks_at_the_reported_rotation(monkeypatch)
    scene = scatter(1, pose_error(1.5, 0.5, 2.0))
    result, _ = antialias_align(*scene.args())
    assert not calls and error_m(result.corrected, scene) < 0.1


def test_hypotheses_switch_off_is_plain_roco():
    scene = lot(0, -1.4, rows=3, per_row=16, origin=-18.0, size_jitter=0.06, collab_x=12.0,
                sensor_range=70.0)
    off, _ = antialias_align(*scene.args(), use_hypotheses=False)
    np.testing.assert_array_equal(off.corrected, roco_align(*scene.args()).corrected)
    on, _ = antialias_align(*scene.args())
    assert error_m(on.corrected, scene) < 0.1 < error_m(off.corrected, scene)


def observation(scene):
    return to_observation(scene, max_boxes=160, max_collaborators=2)


def test_policy_tracks_are_per_ego_and_collaborator():
    """One instance serving two egos: a decision for (ego A, cav_1) informs A's next
    ambiguous step, never ego B's; without ids in the info no track is used (the pose then
    keeps the reported one along the rows: 1.4 m off, one stall from the alias)."""
    clear = lot(1, size_jitter=0.06)
    ambiguous = lot(1)
    policy = make_policy("roco_antialias")
    policy(observation(clear), {"agent": "cav_0", "collaborators": ["cav_1"]})
    follow_a = policy(observation(ambiguous), {"agent": "cav_0", "collaborators": ["cav_1"]})
    follow_b = policy(observation(ambiguous), {"agent": "cav_2", "collaborators": ["cav_1"]})
    anonymous = policy(observation(ambiguous))
    obs = observation(ambiguous)

    def error(action):
        return error_m(apply_correction(obs["collab_rel_poses"], action)[:1], ambiguous)

    assert error(follow_a) < 0.1
    assert error(follow_b) == pytest.approx(1.4, abs=0.02)
    assert error(anonymous) == pytest.approx(1.4, abs=0.02)
    policy.reset()
    after_reset = policy(obs, {"agent": "cav_0", "collaborators": ["cav_1"]})
    assert error(after_reset) == pytest.approx(1.4, abs=0.02)


def test_degenerate_inputs():
    scene = lot(0, size_jitter=0.06)
    empty = np.zeros((0, 7)), np.zeros((0, 3))
    result, decisions = antialias_align(*empty, [*empty[:1]], [empty[1]], scene.reported)
    assert not result.applied[0] and decisions[0].hypotheses == 0
    result, decisions = antialias_align(*scene.args()[:2], [], [], np.zeros((0, 3)))
    assert result.corrected.shape == (0, 3) and decisions == []
    far = antialias_align(*scene.args()[:4], scene.reported + np.array([[40.0, 0.0, 0.0]]))[0]
    np.testing.assert_allclose(far.corrected[0], scene.reported[0] + [40.0, 0.0, 0.0])
    for bad in ({"min_margin": 0.0}, {"search_radius": -1.0}, {"max_hypotheses": 0},
                {"track_max_age": 0}, {"tau2": 0.0}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            antialias_align(*scene.args(), **bad)
    with pytest.raises(ValueError, match="tracks must have one entry"):
        antialias_align(*scene.args(), tracks=[])
    with pytest.raises(ValueError, match="unknown roco_antialias parameter"):
        make_policy("roco_antialias", tau3=1.0)


@pytest.mark.parametrize(("translation_std", "box_std", "thin"), [
    (0.43, 0.33, True),   # an RSU-pair fit that harmed: 1.3 times one pair's precision
    (0.50, 0.47, True),   # at least one pair's precision and THIN_FIT_T
    (0.50, 0.52, False),  # paper_table1_calibrated's boxes (0.3 m each): no thinner than a pair
    (0.25, 0.10, False),  # below THIN_FIT_T however precise the boxes
    (0.35, float("nan"), True),  # box precision unknown: THIN_FIT_T alone
])
def test_thin_fit_is_thin_against_the_boxes_own_precision(translation_std, box_std, thin):
    """A fit is thin from THIN_FIT_T and from THIN_FIT_BOXES times the boxes' own precision
    (one pair's): translation std sqrt(0.5) * s for isotropic information 1 / s^2."""
    s = translation_std / np.sqrt(2.0)
    information = np.diag([1.0 / s**2, 1.0 / s**2, 1e6])
    ambiguity = Ambiguity(np.zeros(3), np.ones(3), np.zeros((0, 3)), information, 5,
                          np.zeros((0, 3)), box_std=box_std)
    assert ambiguity.translation_std == pytest.approx(translation_std, rel=1e-3)
    assert _thin(ambiguity) is thin
