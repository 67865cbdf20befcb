"""Observation modes (scenario section ``observation``): aligned and bev."""

from __future__ import annotations

import numpy as np
import pytest
import shapely
from gymnasium.utils.env_checker import check_env
from hypothesis import given, settings
from hypothesis import strategies as st
from pettingzoo.test import parallel_api_test, parallel_seed_test
from test_conformance import make_parallel, replay_folder  # noqa: F401 - a fixture

import roco_env
from roco_env.geometry import box_corners_bev, se2_compose, se2_inverse, transform_boxes
from roco_env.observation_modes import (
    CHOICE_DIAGNOSTICS,
    DIAGNOSTICS,
    _occupancy,
    bev_shape,
)
from roco_env.scenario import ObservationConfig
from roco_env.wrappers import EgoEnv

CYCLES = 3
# Every shipped scenario; the default run (CI) takes a sample of them, the rest with the
# slow tests (ROCO_SLOW=1): synthetic layouts crowded and plain, a dataset-shaped scene
# and a replay.
SAMPLE = ("urban_intersection", "parking_lot", "v2xset_like", "opv2v_replay")
SCENARIOS = [pytest.param(name, marks=() if name in SAMPLE else pytest.mark.slow)
             for name in roco_env.list_scenarios()]
NOISY = {"sigma_t": 0.8, "sigma_r": 0.8}
COLUMN = {name: k for k, (name, *_) in enumerate(DIAGNOSTICS)}
CHOICE = {name: k for k, (name, *_) in enumerate(CHOICE_DIAGNOSTICS)}
CHOICES = ("identity", "coalign", "roco", "roco_antialias")


@pytest.mark.parametrize("mode", ["aligned", "bev"])
@pytest.mark.parametrize("scenario", SCENARIOS)
def test_every_observation_mode_conforms_on_every_scenario(scenario, mode,
                                                           replay_folder):  # noqa: F811
    overrides = {"observation.mode": mode,
                 "action.mode": "gate" if scenario.startswith("v2x") else "correction"}
    parallel_api_test(make_parallel(scenario, replay_folder, **overrides), num_cycles=CYCLES)
    parallel_seed_test(lambda: make_parallel(scenario, replay_folder, **overrides),
                       num_cycles=CYCLES)
    ego = EgoEnv(env=make_parallel(scenario, replay_folder, **overrides))
    check_env(ego, skip_render_check=True)


@pytest.mark.parametrize("mode", ["aligned", "bev"])
def test_the_spaces_of_the_new_modes_are_bounded(mode):
    env = roco_env.parallel_env("urban_intersection", **{"observation.mode": mode})
    for space in env.observation_space("cav_0").values():
        assert np.isfinite(space.low).all() and np.isfinite(space.high).all()
    if mode == "bev":
        assert env.observation_space("cav_0")["bev"].dtype == np.uint8


def _first_step(action_mode, base="roco", **overrides):
    env = roco_env.parallel_env("urban_intersection", max_cycles=2,
                                **{"observation.mode": "aligned", "action.mode": action_mode,
                                   "action.base": base, **NOISY, **overrides})
    observations, infos = env.reset(seed=4)
    return env, observations, infos


def test_aligned_boxes_are_the_raw_boxes_moved_by_the_reported_pose():
    env, observations, _ = _first_step("correction")
    raw = env._observations["cav_0"]
    view = env._frame.views[0]
    obs = observations["cav_0"]
    n = len(view.collaborators)
    assert n >= 2
    np.testing.assert_allclose(obs["collab_rel_poses"][:n], view.reported_relative,
                               rtol=0, atol=1e-5)
    for slot in range(n):
        count = int(raw["collab_box_mask"][slot].sum())
        expected = transform_boxes(raw["collab_boxes"][slot, :count], view.reported_relative[slot])
        np.testing.assert_allclose(obs["collab_boxes"][slot, :count], expected, rtol=0, atol=1e-4)
        assert not obs["collab_boxes"][slot, count:].any()


def _shared_object_gaps(action_mode, base):
    """Ego-frame centre distances (m) of cav_0's and its collaborators' boxes of one object."""
    _, observations, infos = _first_step(action_mode, base=base)
    obs, privileged = observations["cav_0"], infos["cav_0"]["privileged"]
    mine = dict(zip(privileged["box_object_ids"], obs["boxes"], strict=True))
    return [np.hypot(*(box[:2] - mine[oid][:2]))
            for slot in range(int(obs["collab_mask"].sum()))
            for oid, box in zip(privileged["collab_box_object_ids"][slot],
                                obs["collab_boxes"][slot], strict=True)
            if oid >= 0 and oid in mine]


def test_aligned_through_the_oracle_puts_shared_objects_on_the_egos_boxes():
    """In gate mode the boxes move through the base aligner's pose (the oracle's: the truth);
    in correction mode through the reported one."""
    true_gaps = _shared_object_gaps("gate", "oracle")
    reported_gaps = _shared_object_gaps("correction", "oracle")
    assert len(true_gaps) == len(reported_gaps) >= 5
    assert np.median(true_gaps) < 0.5  # both views' detection noise only
    assert np.median(reported_gaps) > 2 * np.median(true_gaps)


def test_diagnostics_describe_the_base_aligners_call():
    env, observations, _ = _first_step("residual")
    obs = observations["cav_0"]
    view = env._frame.views[0]
    alignment = env._alignments["cav_0"]
    rows = obs["diagnostics"]
    n = len(view.collaborators)
    np.testing.assert_array_equal(rows[:n, COLUMN["applied"]], alignment.result.applied[:n])
    np.testing.assert_allclose(rows[:n, COLUMN["distance_m"]],
                               np.hypot(*view.reported_relative[:, :2].T), rtol=1e-6)
    np.testing.assert_array_equal(rows[:n, COLUMN["boxes"]],
                                  [len(s) for s in view.collab_scores])
    assert rows[:n, COLUMN["pairs"]].sum() > 0
    paired = rows[:n, COLUMN["pairs"]] > 0
    assert (rows[:n, COLUMN["residual_m"]][paired] < 1.0).all()  # roco's pose fits its pairs
    assert (rows[n:] == np.where(np.arange(len(DIAGNOSTICS)) == COLUMN["statistic"], -1, 0)).all()


@pytest.mark.parametrize("late", [False, True])
def test_the_age_column_is_the_held_scans_age(late):
    """Under a delay (comm.delay fixed 200 ms, 10 Hz: two frames late) each slot's age_ms
    is the age of the scan the ego holds; without the network stage it is 0."""
    env, observations, _ = _first_step(
        "correction", **({"comm.delay": "fixed", "comm.delay_params.delay_ms": 200}
                         if late else {}))
    ages = []
    for _ in range(3):  # the first frames of a late episode may hold no scan yet
        view = env._frame.views[0]
        n = len(view.collaborators)
        column = observations["cav_0"]["diagnostics"][:, COLUMN["age_ms"]]
        expected = 1000.0 * view.collab_age if late else np.zeros(n)
        np.testing.assert_allclose(column[:n], expected, rtol=1e-6)
        assert not column[n:].any()
        ages += column[:n].tolist()
        if not env.agents:
            break
        observations, *_ = env.step({a: np.zeros((env.config.max_collaborators, 3), np.float32)
                                      for a in env.agents})
    assert (max(ages) >= 200.0) if late else (max(ages, default=0.0) == 0.0)


@pytest.mark.parametrize("scenario", ["opv2v_replay",
                                      pytest.param("urban_intersection", marks=pytest.mark.slow)])
def test_select_mode_with_the_aligned_observation_conforms(scenario,
                                                          replay_folder):  # noqa: F811
    overrides = {"observation.mode": "aligned", "action.mode": "select"}
    parallel_api_test(make_parallel(scenario, replay_folder, **overrides), num_cycles=CYCLES)
    parallel_seed_test(lambda: make_parallel(scenario, replay_folder, **overrides),
                       num_cycles=CYCLES)
    check_env(EgoEnv(env=make_parallel(scenario, replay_folder, **overrides)),
              skip_render_check=True)


def test_select_mode_shows_every_choices_diagnostics_and_agreement():
    env, observations, _ = _first_step("select")
    rows = observations["cav_0"]["choice_diagnostics"]
    assert rows.shape == (5, len(CHOICES), len(CHOICE_DIAGNOSTICS))
    assert env.observation_space("cav_0")["choice_diagnostics"].contains(rows)
    view = env._frame.views[0]
    n = len(view.collaborators)
    poses = np.stack([a.corrected for a in env.action_mode._observed["cav_0"]])  # (C, n, 3)
    for k in range(len(CHOICES)):
        change = se2_compose(poses[k], se2_inverse(view.reported_relative))
        shift = np.hypot(change[:, 0], change[:, 1])
        np.testing.assert_allclose(rows[:n, k, CHOICE["shift_m"]], np.minimum(shift, 20.0),
                                   rtol=1e-5, atol=1e-5)
    identity = rows[:n, CHOICES.index("identity")]
    assert not identity[:, CHOICE["applied"]].any() and not identity[:, CHOICE["pairs"]].any()
    for slot in range(n):
        for k in range(len(CHOICES)):
            gaps = [np.hypot(*(poses[k, slot, :2] - poses[j, slot, :2]))
                    for j in range(len(CHOICES)) if j != k]
            turns = [abs(np.degrees(poses[k, slot, 2] - poses[j, slot, 2]))
                     for j in range(len(CHOICES)) if j != k]
            assert rows[slot, k, CHOICE["gap_m"]] == pytest.approx(min(min(gaps), 20.0),
                                                                   abs=1e-5)
            assert rows[slot, k, CHOICE["agreeing"]] == sum(
                g <= 1.0 and t <= 1.0 for g, t in zip(gaps, turns, strict=True))
    assert (rows[n:] == np.where(np.arange(len(CHOICE_DIAGNOSTICS)) == CHOICE["statistic"],
                                 -1, 0)).all()
    gate_env, gate_observations, _ = _first_step("gate")
    assert "choice_diagnostics" not in gate_observations["cav_0"]
    assert "choice_diagnostics" not in gate_env.observation_space("cav_0").spaces


def test_a_base_aligner_among_the_choices_runs_once_and_describes_the_same():
    """select + aligned with action.base among the choices takes the base's alignment from
    that choice (no second instance runs): its diagnostics are those of gate mode, where
    the base aligner runs alone."""
    select_env, select_obs, _ = _first_step("select", base="roco_antialias")
    gate_env, gate_obs, _ = _first_step("gate", base="roco_antialias")
    assert select_env.base_aligner is None and gate_env.base_aligner is not None
    for agent in select_env.possible_agents:
        np.testing.assert_array_equal(select_obs[agent]["diagnostics"],
                                      gate_obs[agent]["diagnostics"])


def test_select_decisions_are_the_same_whatever_the_observation():
    """With the aligned observation every choice runs once per observation and the action
    reuses those poses; the episode equals the raw-observation one, where a stateless
    choice runs only when picked (the same random picks, the same rewards and errors)."""
    def episode(mode):
        env = roco_env.parallel_env("urban_intersection", max_cycles=4, reward="ap70_gain",
                                    **{"observation.mode": mode, "action.mode": "select",
                                       "sigma_t": 1.5, "sigma_r": 1.5})
        env.reset(seed=3)
        picks, out = np.random.default_rng(0), []
        while env.agents:
            _, rewards, _, _, infos = env.step(
                {a: picks.integers(0, len(CHOICES) + 1, 5) for a in env.agents})
            out += [(rewards[a], infos[a]["rpe_after"].tolist()) for a in sorted(rewards)]
        return out

    assert episode("aligned") == episode("raw")


def test_bev_channels_put_forward_up_and_left_left():
    config = ObservationConfig(mode="bev", bev_range=20.0, bev_resolution=1.0)
    h, w = bev_shape(config)
    xs = 20.0 - (np.arange(h) + 0.5)
    ys = 20.0 - (np.arange(w) + 0.5)
    ahead = _occupancy(np.array([[10.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0]]), xs, ys)
    left = _occupancy(np.array([[0.0, 10.0, 0.0, 4.0, 2.0, 1.5, 0.0]]), xs, ys)
    rows, cols = np.nonzero(ahead)
    assert rows.max() < h / 2 and abs(cols.mean() - (w - 1) / 2) < 1
    rows, cols = np.nonzero(left)
    assert cols.max() < w / 2 and abs(rows.mean() - (h - 1) / 2) < 1
    assert ahead.sum() // 255 == 8  # 4 m x 2 m on 1 m cells


@settings(max_examples=80, deadline=None)
@given(x=st.floats(-25, 25), y=st.floats(-25, 25), length=st.floats(0.5, 12),
       width=st.floats(0.5, 4), yaw=st.floats(-np.pi, np.pi))
def test_occupancy_marks_exactly_the_cells_whose_centre_is_inside(x, y, length, width, yaw):
    """Against shapely's point-in-polygon on every cell centre (cells on the edge skipped)."""
    xs = 20.0 - (np.arange(40) + 0.5)
    ys = 20.0 - (np.arange(40) + 0.5)
    box = np.array([[x, y, 0.0, length, width, 1.5, yaw]])
    polygon = shapely.Polygon(box_corners_bev(box)[0])
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    points = shapely.points(gx.ravel(), gy.ravel())
    inside = shapely.contains(polygon, points).reshape(gx.shape)
    edge = (shapely.distance(polygon.exterior, points) < 1e-9).reshape(gx.shape)
    got = _occupancy(box, xs, ys) == 255
    assert (got == inside)[~edge].all()


def test_bev_observation_holds_each_collaborators_boxes():
    env = roco_env.parallel_env("urban_intersection", max_cycles=2,
                                **{"observation.mode": "bev", **NOISY})
    observations, _ = env.reset(seed=4)
    bev = observations["cav_0"]["bev"]
    n = int(observations["cav_0"]["collab_mask"].sum())
    assert bev.shape[0] == env.config.max_collaborators + 1
    assert bev[0].any() and all(bev[1 + j].any() for j in range(n))
    assert not bev[1 + n:].any()
    assert set(np.unique(bev)) <= {0, 255}


def test_an_unknown_observation_mode_names_the_field():
    with pytest.raises(ValueError, match=r"observation\.mode"):
        roco_env.parallel_env("urban_intersection", **{"observation.mode": "pixels"})
