"""Action modes (scenario section ``action``), gain rewards, lean infos and the ego env.

Each mode's defining equality is checked exactly, on the env's own episodes: a zero
residual is the base aligner, selecting aligner k is aligner k, gating keeps the base
aligner, and a rejected collaborator's boxes (late) or map (intermediate) are exactly
what fusion leaves out.
"""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import parallel_api_test, parallel_seed_test
from test_conformance import make_parallel, replay_folder  # noqa: F401 - a fixture

import roco_env
from roco_env.env import METRIC_INFO_KEYS
from roco_env.fusion import merge_many, suppress
from roco_env.metrics import in_range_mask
from roco_env.policies import make_policy
from roco_env.scenario import ConfigError
from roco_env.wrappers import EgoEnv

MODES = ("residual", "select", "gate")
CYCLES = 3
# Every shipped scenario; the default run (CI) takes a sample of them, the rest with the
# slow tests (ROCO_SLOW=1): synthetic layouts crowded and plain, a dataset-shaped scene
# and a replay.
SAMPLE = ("urban_intersection", "parking_lot", "v2xset_like", "opv2v_replay")
SCENARIOS = [pytest.param(name, marks=() if name in SAMPLE else pytest.mark.slow)
             for name in roco_env.list_scenarios()]
NOISY = {"sigma_t": 0.8, "sigma_r": 0.8}


def env_in(mode, scenario="urban_intersection", steps=4, **overrides):
    return roco_env.parallel_env(scenario, max_cycles=steps,
                                 **{"action.mode": mode, **NOISY, **overrides})


def rewards_with(env, act, seed=0):
    """Per-step rewards of every agent when ``act(agent, observation, info)`` acts."""
    observations, infos = env.reset(seed=seed)
    history = []
    while env.agents:
        actions = {a: act(a, observations[a], infos[a]) for a in env.agents}
        observations, rewards, _, _, infos = env.step(actions)
        history.append(rewards)
    return history


def policy_driver(name):
    """``act`` of one fresh ``name`` instance per agent (as a sweep runs a policy)."""
    policies = {}

    def act(agent, observation, info):
        policy = policies.setdefault(agent, make_policy(name))
        return policy(observation, info)

    return act


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("scenario", SCENARIOS)
def test_every_mode_conforms_on_every_scenario(scenario, mode, replay_folder):  # noqa: F811
    overrides = {"action.mode": mode}
    parallel_api_test(make_parallel(scenario, replay_folder, **overrides), num_cycles=CYCLES)
    parallel_seed_test(lambda: make_parallel(scenario, replay_folder, **overrides),
                       num_cycles=CYCLES)
    ego = EgoEnv(env=make_parallel(scenario, replay_folder, **overrides))
    check_env(ego, skip_render_check=True)


def test_a_zero_residual_is_the_base_aligner_exactly():
    base = rewards_with(env_in("correction"), policy_driver("roco"))
    zero = rewards_with(env_in("residual", **{"action.base": "roco"}),
                        lambda a, o, i: np.zeros((5, 3), np.float32))
    assert zero == base
    assert any(r != 0 for step in base for r in step.values())


def test_a_residual_moves_the_base_pose_by_its_scale():
    env = env_in("residual", steps=1, **{"action.base": "identity", "action.scale": [2, 1, 3]})
    _, infos = env.reset(seed=0)
    action = np.tile(np.float32([0.5, -1.0, 2.0]), (5, 1))  # dyaw clipped to 1 -> 3 degrees
    _, _, _, _, after = env.step({a: action for a in env.agents})
    moved = roco_env.parallel_env("urban_intersection", max_cycles=1, **NOISY)
    moved.reset(seed=0)
    correction = np.tile([1.0, -1.0, np.radians(3.0)], (5, 1)).astype(np.float32)
    _, _, _, _, expected = moved.step({a: correction for a in moved.agents})
    for agent in env.possible_agents:
        np.testing.assert_allclose(after[agent]["rpe_after"], expected[agent]["rpe_after"],
                                   rtol=0, atol=1e-5)  # float32 vs float64 scale product


@pytest.mark.parametrize("choice", ["identity", "coalign", "roco", "roco_antialias"])
def test_selecting_aligner_k_is_aligner_k(choice):
    choices = ["identity", "coalign", "roco", "roco_antialias"]
    k = choices.index(choice)
    selected = rewards_with(env_in("select"), lambda a, o, i: np.full(5, k))
    assert selected == rewards_with(env_in("correction"), policy_driver(choice))


def test_gate_keeping_every_slot_is_the_base_aligner():
    kept = rewards_with(env_in("gate", **{"action.base": "coalign"}),
                        lambda a, o, i: np.zeros(5, np.int64))
    assert kept == rewards_with(env_in("correction"), policy_driver("coalign"))


def test_select_reject_index_and_gate_reject_agree():
    reject_all_select = rewards_with(env_in("select"), lambda a, o, i: np.full(5, 4))
    reject_all_gate = rewards_with(env_in("gate"), lambda a, o, i: np.ones(5, np.int64))
    alone = rewards_with(env_in("correction", fusion="none"), lambda a, o, i: np.zeros((5, 3)))
    assert reject_all_select == reject_all_gate == alone


LIAR = {"attack.kind": "ghost", "attack.agents": ["cav_1"],
        "attack.params": {"n_ghost": 20, "placement": "aliasing"}}


def _honest_poses(attack, reject_liar, base="roco"):
    """Per step and honest ego, the pose errors after (rpe_after) of its honest collaborator
    slots, in gate mode behind ``base``, cav_1 rejected by every ego or kept."""
    env = env_in("gate", steps=3, **{"action.base": base, **attack})
    observations, infos = env.reset(seed=0)
    poses = []
    while env.agents:
        slots = {a: infos[a]["collaborators"] for a in env.agents}
        actions = {a: np.array([int(reject_liar and s == "cav_1") for s in slots[a]]
                               + [0] * (5 - len(slots[a]))) for a in env.agents}
        observations, _, _, _, infos = env.step(actions)
        poses.append({a: infos[a]["rpe_after"][[k for k, s in enumerate(slots[a])
                                                 if s != "cav_1"]]
                      for a in env.possible_agents if a != "cav_1"})
    return poses


def _same(a, b):
    return all(x.keys() == y.keys() and all(np.array_equal(x[k], y[k]) for k in x)
               for x, y in zip(a, b, strict=True))


@pytest.mark.parametrize("base", ["roco", "roco_antialias"])
def test_a_rejected_collaborator_no_longer_moves_the_kept_ones(base):
    """Behind a joint aligner the liar's boxes pull the honest collaborators' poses; once
    the gate rejects it, they are solved again without it: exactly the poses of the same
    episode without the attack (the attack changes only the liar's messages)."""
    assert not _same(_honest_poses(LIAR, False, base), _honest_poses({}, False, base))
    assert _same(_honest_poses(LIAR, True, base), _honest_poses({}, True, base))


def _one_ego_env(fusion_overrides):
    return roco_env.parallel_env("urban_intersection", max_cycles=2,
                                 **{"action.mode": "gate", "action.base": "identity",
                                    "agents.evaluated": ["cav_0"], **NOISY,
                                    **fusion_overrides})


def _expected_without(env, slot, intermediate):
    """cav_0's fused boxes with collaborator ``slot`` left out, built from the stages."""
    frame = env._frame
    view = frame.views[0]
    keep = np.arange(len(view.collaborators)) != slot
    poses = view.reported_relative[keep]
    if intermediate:
        from roco_env.fusion.intermediate import intermediate_fusion

        merged = intermediate_fusion(
            env.pipeline.detector, frame.encoder_maps, frame.state, [0],
            [[j for j, k in zip(view.collaborators, keep, strict=True) if k]], [poses],
            env.config.evaluation.x_range, env.config.evaluation.y_range)
    else:
        merged = merge_many([(view.boxes, view.scores,
                              [b for b, k in zip(view.collab_boxes, keep, strict=True) if k],
                              [s for s, k in zip(view.collab_scores, keep, strict=True) if k],
                              poses)])
    fused = suppress(merged, env.config.fusion.nms_iou, [frame.footprints[0]])[0]
    scored = in_range_mask(fused.boxes, env.config.evaluation.x_range,
                           env.config.evaluation.y_range)  # the info's boxes: those scored
    return fused.boxes[scored], fused.scores[scored]


@pytest.mark.parametrize("fusion", [
    {"fusion": "late"},
    pytest.param({"fusion": "intermediate", "detector": "learned"}, marks=pytest.mark.slow),
], ids=["late", "intermediate"])
def test_reject_leaves_out_exactly_that_collaborator(fusion):
    env = _one_ego_env(fusion)
    env.reset(seed=1)
    assert len(env._frame.views[0].collaborators) >= 2
    expected = _expected_without(env, 1, "intermediate" in fusion.values())
    action = np.zeros(5, np.int64)
    action[1] = 1
    _, _, _, _, infos = env.step({a: action for a in env.agents})
    info = infos["cav_0"]
    assert info["rejected"].tolist() == [False, True, False, False, False]
    boxes, scores = expected
    np.testing.assert_array_equal(info["fused_boxes"][info["fused_mask"]], boxes)
    np.testing.assert_array_equal(info["fused_scores"][info["fused_mask"]], scores)


def test_reject_changes_fusion_only_for_that_collaborator():
    """Rejecting a slot that holds nothing useful is not the same as rejecting all."""
    env = _one_ego_env({"fusion": "late"})
    env.reset(seed=1)
    keep_all = _expected_without(env, -1, False)
    without_one = _expected_without(env, 1, False)
    assert keep_all[0].shape[0] > without_one[0].shape[0]


def test_gain_reward_is_the_fused_ap_minus_the_own_ap():
    zeros = lambda a, o, i: np.zeros((5, 3))  # noqa: E731
    gain = rewards_with(env_in("correction", reward="ap70_gain"), zeros)
    fused = rewards_with(env_in("correction"), zeros)
    alone = rewards_with(env_in("correction", fusion="none"), zeros)
    for g, f, a in zip(gain, fused, alone, strict=True):
        assert g == {agent: f[agent] - a[agent] for agent in g}
    assert any(v < 0 for step in gain for v in step.values())  # identity harms at 0.8
    none_gain = rewards_with(env_in("correction", fusion="none", reward="ap50_gain"), zeros)
    assert all(v == 0.0 for step in none_gain for v in step.values())


def test_a_correction_at_the_bound_scores_below_no_fusion():
    """The push-away exploit is closed: no correction inside the bounds emulates a reject."""
    env = env_in("correction", steps=8)
    bound = env.action_space("cav_0").high[0, 1]
    assert bound <= 20.0
    push = np.tile(np.float32([0.0, bound, 0.0]), (5, 1))
    pushed = rewards_with(env, lambda a, o, i: push)
    alone = rewards_with(env_in("correction", steps=8, fusion="none"),
                         lambda a, o, i: np.zeros((5, 3)))
    total = sum(sum(step.values()) for step in pushed)
    assert total < sum(sum(step.values()) for step in alone)


def test_metrics_and_none_info_levels_are_lean():
    env = env_in("correction", info_level="metrics")
    _, infos = env.reset(seed=0)
    assert "privileged" not in infos["cav_0"]
    _, _, _, _, infos = env.step({a: np.zeros((5, 3)) for a in env.agents})
    assert set(infos["cav_0"]) == set(METRIC_INFO_KEYS)
    full = env_in("correction")
    full.reset(seed=0)
    _, _, _, _, full_infos = full.step({a: np.zeros((5, 3)) for a in full.agents})
    for key in METRIC_INFO_KEYS:
        np.testing.assert_array_equal(infos["cav_0"][key], full_infos["cav_0"][key])
    bare = env_in("correction", info_level="none")
    _, infos = bare.reset(seed=0)
    assert infos["cav_0"] == {}
    asked = env_in("correction", info_level="none", privileged=True)
    _, infos = asked.reset(seed=0)
    assert set(infos["cav_0"]) == {"privileged"}


def test_the_oracle_as_a_choice_works_without_privileged_infos():
    lean = env_in("select", info_level="none", **{"action.choices": ["identity", "oracle"]})
    full = env_in("select", **{"action.choices": ["identity", "oracle"]})
    pick_oracle = lambda a, o, i: np.ones(5, np.int64)  # noqa: E731
    assert rewards_with(lean, pick_oracle) == rewards_with(full, pick_oracle)


def test_the_ego_env_scores_only_its_agent_unless_told():
    lean = EgoEnv("urban_intersection", max_cycles=3, agent="cav_1", **NOISY)
    assert lean.env.evaluated_agents == ["cav_1"]
    every = EgoEnv("urban_intersection", max_cycles=3, agent="cav_1", evaluate_others=True,
                   **NOISY)
    assert every.env.evaluated_agents == every.env.possible_agents
    for env in (lean, every):
        env.reset(seed=2)
    for _ in range(3):
        action = np.zeros((5, 3), np.float32)
        _, r_lean, _, _, i_lean = lean.step(action)
        _, r_every, _, _, i_every = every.step(action)
        assert r_lean == r_every and i_lean["ap70"] == i_every["ap70"]


def test_the_ego_env_others_take_the_neutral_action_of_the_mode():
    ego = EgoEnv("urban_intersection", max_cycles=2, **{"action.mode": "select"})
    ego.reset(seed=0)
    ego.step(ego.action_space.sample())  # the others' default must be a valid index


def test_the_ego_env_registered_with_gymnasium_takes_a_mode():
    env = gymnasium.make("roco/CollabPerceptionEgo-v0", scenario="urban_roundabout",
                         max_cycles=2, info_level="metrics", **{"action.mode": "gate"})
    env.reset(seed=0)
    _, reward, _, _, info = env.step(env.action_space.sample())
    assert isinstance(reward, float) and "privileged" not in info


@pytest.mark.parametrize("overrides, field", [
    ({"action.mode": "steer"}, "action.mode"),
    ({"action.mode": "residual", "action.base": "nonesuch"}, "action.base"),
    ({"action.mode": "gate", "action.base": "roco:tau2=-1"}, "action.base"),
    ({"action.mode": "select", "action.choices": ["identity", "nonesuch"]}, "action.choices"),
    ({"action.mode": "select", "action.choices": []}, "action.choices"),
    ({"action.mode": "select", "action.choices": ["roco", "roco"]}, "action.choices"),
    ({"action.mode": "residual", "action.scale": [1.0, 0.0, 1.0]}, "action.scale"),
    ({"action.mode": "residual", "action.scale": [1.0, 1.0]}, "action.scale"),
    ({"action.max_translation": 140.0}, "action.max_translation"),
])
def test_bad_action_settings_name_the_field(overrides, field):
    with pytest.raises((ValueError, ConfigError), match=field.replace(".", r"\.")):
        roco_env.parallel_env("urban_intersection", **overrides)


@pytest.mark.parametrize("mode, action", [
    ("select", np.full(5, 5)),
    ("select", np.full(5, -1)),
    ("select", np.full(5, 1.5)),
    ("gate", np.full(5, 2)),
    ("gate", np.ones(5, bool)),
    ("gate", np.zeros(4, np.int64)),
    ("residual", np.full((5, 3), np.nan)),
])
def test_bad_actions_name_the_agent(mode, action):
    env = env_in(mode)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="cav_0"):
        env.step({a: action for a in env.agents})


def test_bad_info_levels_are_refused():
    with pytest.raises(ValueError, match="info_level"):
        roco_env.parallel_env("urban_intersection", info_level="some")
    with pytest.raises(ValueError, match="privileged"):
        roco_env.parallel_env("urban_intersection", privileged="yes")


def test_flatten_actions_refuses_discrete_modes():
    from roco_env.wrappers import FlattenActions

    with pytest.raises(ValueError, match="MultiDiscrete"):
        FlattenActions(env_in("select"))
