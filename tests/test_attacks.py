"""The attack stage (roco_env.attacks): who attacks, what each attack changes in the
messages and nothing else, the privileged truth, and the bad inputs."""

from __future__ import annotations

import numpy as np
import pytest

import roco_env
from roco_env.attacks.ghost import GHOST_SIZE
from roco_env.attacks.pose import PoseSpoof, offset_pose
from roco_env.geometry import se2_compose, se2_relative, transform_boxes
from roco_env.pipeline import Pipeline
from roco_env.scenario import ConfigError, load_scenario

SCENE = "urban_intersection"  # 4 CAVs and 1 RSU
NOISE = {"sigma_t": 0.4, "sigma_r": 0.4}


def frame(seed: int = 0, steps: int = 0, **attack):
    """The pipeline's frame after ``steps`` advances with the given ``attack.*`` fields."""
    config = load_scenario(SCENE, **NOISE, **{f"attack.{k}": v for k, v in attack.items()})
    pipeline = Pipeline(config)
    out = pipeline.reset(np.random.default_rng(seed))
    for _ in range(steps):
        out = pipeline.advance()
    return pipeline, out


def same_view_except(clean, attacked, attacker: int) -> None:
    """Everything of ``attacked``'s views equals ``clean``'s but the slots of ``attacker``."""
    assert np.array_equal(clean.state.agent_poses, attacked.state.agent_poses)
    assert np.array_equal(clean.reported_poses, attacked.reported_poses)
    for before, after in zip(clean.views, attacked.views, strict=True):
        assert before.collaborators == after.collaborators
        assert np.array_equal(before.pose, after.pose)
        assert np.array_equal(before.boxes, after.boxes)
        for slot, sender in enumerate(before.collaborators):
            if sender == attacker and before.agent != attacker:
                continue
            assert np.array_equal(before.collab_poses[slot], after.collab_poses[slot])
            assert np.array_equal(before.collab_boxes[slot], after.collab_boxes[slot])
            assert np.array_equal(before.collab_object_ids[slot], after.collab_object_ids[slot])


def attacked_slots(view, attacker: int) -> list[int]:
    return [slot for slot, j in enumerate(view.collaborators) if j == attacker]


def test_the_attack_draws_from_its_own_stream_leaving_the_episode_as_it_was():
    _, clean = frame(steps=2)
    for kind, params in (("pose_spoof", {"offset_m": 5.0}), ("ghost", {"n_ghost": 7}),
                         ("erase", {"share": 0.5})):
        pipeline, attacked = frame(steps=2, kind=kind, params=params)
        (attacker,) = pipeline.attack.attackers
        same_view_except(clean, attacked, attacker)


def test_without_an_attack_an_episode_is_the_one_played_before_the_attack_stage_existed():
    """Numbers recorded with the code before the attack stage (and its child stream)."""
    env = roco_env.parallel_env(SCENE, max_cycles=3, **NOISE)
    observations, _ = env.reset(seed=7)
    assert [int(o["box_mask"].sum()) for o in observations.values()] == [23, 29, 24, 22, 42]
    assert [int(o["collab_box_mask"].sum()) for o in observations.values()] == \
        [117, 111, 116, 118, 98]
    rewards = [list(env.step({a: np.zeros((5, 3)) for a in env.agents})[1].values())
               for _ in range(3)]
    assert rewards[0] == pytest.approx([0.088573360379, 0.125668449198, 0.153151260504,
                                        0.257347180267, 0.331543728603], abs=1e-9)
    assert rewards[2] == pytest.approx([0.296867820827, 0.206102275621, 0.23011628894,
                                        0.335824389731, 0.282700016033], abs=1e-9)


def test_attackers_are_drawn_per_episode_from_the_seed_or_named():
    drawn = set()
    for seed in range(12):
        pipeline, _ = frame(seed, kind="erase")
        assert len(pipeline.attack.attackers) == 1
        assert pipeline.attack.attackers == frame(seed, kind="erase")[0].attack.attackers
        drawn.add(pipeline.attack.attackers)
    assert len(drawn) > 1  # the seed chooses
    pipeline, _ = frame(kind="erase", count=2)
    assert len(pipeline.attack.attackers) == 2
    pipeline, _ = frame(kind="erase", agents=["rsu_0", "cav_2"])
    assert pipeline.attack.attackers == (2, 4)


def test_a_consistent_spoof_moves_exactly_the_attackers_pose_and_unshared_boxes():
    offset_m, offset_deg = 6.0, 4.0
    _, clean = frame(steps=1)
    pipeline, attacked = frame(steps=1, kind="pose_spoof", agents=["cav_1"],
                               params={"offset_m": offset_m, "offset_deg": offset_deg,
                                       "direction_deg": 90.0, "consistent": True})
    same_view_except(clean, attacked, 1)
    offset = offset_pose(offset_m, 90.0, offset_deg)
    checked = {"shared": 0, "own": 0}
    for before, after in zip(clean.views, attacked.views, strict=True):
        for slot in attacked_slots(before, 1) if before.agent != 1 else []:
            assert np.allclose(after.collab_poses[slot], se2_compose(before.collab_poses[slot],
                                                                     offset))
            ids = before.collab_object_ids[slot]
            assert np.array_equal(ids, after.collab_object_ids[slot])
            shared = np.isin(ids, clean.detections[before.agent].object_ids) & (ids >= 0)
            # where the victim puts them: the shared boxes where honesty would, the rest moved
            honest = transform_boxes(before.collab_boxes[slot], before.reported_relative[slot])
            lied = transform_boxes(after.collab_boxes[slot], after.reported_relative[slot])
            assert np.allclose(lied[shared], honest[shared], atol=1e-9)
            assert np.array_equal(after.collab_boxes[slot][~shared],
                                  before.collab_boxes[slot][~shared])
            assert np.all(np.hypot(*(lied[~shared, :2] - honest[~shared, :2]).T) > 1.0)
            checked["shared"] += int(shared.sum())
            checked["own"] += int((~shared).sum())
    assert checked["shared"] > 0 and checked["own"] > 0


def test_a_plain_spoof_moves_every_box_by_the_lie_and_drift_ramps_it():
    _, clean = frame()
    _, attacked = frame(kind="pose_spoof", agents=["cav_0"], params={"offset_m": 3.0})
    victim = attacked.views[1]
    (slot,) = attacked_slots(victim, 0)
    assert np.array_equal(victim.collab_boxes[slot], clean.views[1].collab_boxes[slot])
    config = load_scenario(SCENE, **{"attack.kind": "pose_spoof", "attack.agents": ["cav_0"],
                                     "attack.params": {"offset_m": 4.0, "drift": 2.0}})
    spoof = PoseSpoof(config, ("cav_0", "cav_1"))
    assert np.allclose(spoof.offset(0.0), 0.0)
    assert np.allclose(spoof.offset(1.0), [2.0, 0.0, 0.0])
    assert np.allclose(spoof.offset(5.0), [4.0, 0.0, 0.0])


@pytest.mark.parametrize("placement", ["random", "lanes", "aliasing"])
def test_ghosts_appear_only_in_the_attackers_messages(placement):
    n_ghost = 6
    _, clean = frame(steps=1)
    _, attacked = frame(steps=1, kind="ghost", agents=["cav_2"],
                        params={"n_ghost": n_ghost, "placement": placement})
    same_view_except(clean, attacked, 2)
    victims = 0
    for before, after in zip(clean.views, attacked.views, strict=True):
        for slot in attacked_slots(before, 2) if before.agent != 2 else []:
            ids, sent = after.collab_object_ids[slot], before.collab_object_ids[slot]
            kept = np.ones(sent.shape[0], dtype=bool)
            if placement == "aliasing":  # what supports the true pose is withheld
                kept = ~(np.isin(sent, clean.detections[before.agent].object_ids) & (sent >= 0))
                assert 0 < kept.sum() < kept.shape[0]
            real = int(kept.sum())
            assert np.array_equal(ids[:real], sent[kept])
            assert np.all(ids[real:] == -1) and ids.shape[0] == real + n_ghost
            assert np.array_equal(after.collab_boxes[slot][:real], before.collab_boxes[slot][kept])
            assert np.array_equal(after.collab_poses[slot], before.collab_poses[slot])
            victims += 1
    assert victims > 0


def test_aliasing_ghosts_land_on_the_victims_boxes_under_the_wrong_hypothesis():
    shift = {"shift_m": 4.0, "shift_deg": 3.0, "direction_deg": 45.0}
    _, attacked = frame(kind="ghost", agents=["cav_3"],
                        params={"n_ghost": 5, "placement": "aliasing", **shift})
    delta = offset_pose(shift["shift_m"], shift["direction_deg"], shift["shift_deg"])
    victim = attacked.views[0]
    (slot,) = attacked_slots(victim, 3)
    ghosts = victim.collab_boxes[slot][-5:]  # appended after the real boxes
    assert np.all(victim.collab_object_ids[slot][-5:] == -1)
    landed = transform_boxes(ghosts, se2_compose(delta, victim.reported_relative[slot]))
    own = victim.boxes
    nearest = np.min(np.hypot(landed[:, None, 0] - own[None, :, 0],
                              landed[:, None, 1] - own[None, :, 1]), axis=1)
    assert np.all(nearest < 1e-6)


def test_random_and_lane_ghosts_are_car_sized_and_a_message_keeps_at_most_k_boxes():
    _, attacked = frame(kind="ghost", agents=["cav_0"], params={"n_ghost": 1000,
                                                                 "placement": "lanes"})
    victim = attacked.views[1]
    (slot,) = attacked_slots(victim, 0)
    assert victim.collab_boxes[slot].shape[0] == 64  # max_boxes
    ghosts = victim.collab_boxes[slot][victim.collab_object_ids[slot] == -1]
    assert ghosts.shape[0] > 64 // 2  # they outscore most real boxes
    assert np.allclose(ghosts[-10:, 3:6], GHOST_SIZE)  # appended after the real boxes


def test_erase_withholds_the_named_objects_and_a_share_of_the_rest():
    _, clean = frame()
    victim, attacker = 1, 0
    (slot,) = attacked_slots(clean.views[victim], attacker)
    sent = clean.views[victim].collab_object_ids[slot]
    named = [int(i) for i in sent[sent >= 0][:2]]
    _, attacked = frame(kind="erase", agents=["cav_0"], params={"share": 0.0, "objects": named})
    kept = attacked.views[victim].collab_object_ids[slot]
    assert set(kept.tolist()) == set(sent.tolist()) - set(named)
    _, all_of_it = frame(kind="erase", agents=["cav_0"], params={"share": 1.0})
    assert all_of_it.views[victim].collab_boxes[slot].shape == (0, 7)
    _, hidden = frame(kind="erase", agents=["cav_0"], params={"share": 1.0, "hidden_only": True})
    left = hidden.views[victim].collab_object_ids[slot]
    assert left.size and np.all(np.isin(left, clean.detections[victim].object_ids))


def test_the_attackers_identity_reaches_infos_privileged_but_never_an_observation():
    def episode(agents):
        env = roco_env.parallel_env(SCENE, max_cycles=2, **{
            "attack.kind": "erase", "attack.agents": agents, "attack.params": {"share": 0.0}})
        observations, infos = env.reset(seed=1)
        zeros = {a: np.zeros((5, 3)) for a in env.agents}
        return [observations, env.step(zeros)[0]], infos

    first, infos_first = episode(["cav_1"])
    second, infos_second = episode(["rsu_0"])
    for a, b in zip(first, second, strict=True):  # an attack that changes nothing shows nothing
        for agent in a:
            assert a[agent].keys() == b[agent].keys()
            for key in a[agent]:
                assert np.array_equal(a[agent][key], b[agent][key]), (agent, key)
    assert infos_first["cav_1"]["privileged"]["attacker"]
    assert not infos_second["cav_1"]["privileged"]["attacker"]
    slots = infos_first["cav_0"]["collaborators"]
    assert infos_first["cav_0"]["privileged"]["collab_attackers"].tolist()[: len(slots)] == \
        [s == "cav_1" for s in slots]


@pytest.mark.parametrize("attack, match", [
    ({"kind": "pose_spoof", "agents": ["cav_9"]}, r"attack.agents: 'cav_9' is not an agent"),
    ({"kind": "ghost", "agents": ["cav_0", "cav_1", "cav_2", "cav_3", "rsu_0"]},
     "names every agent"),
    ({"kind": "ghost", "agents": ["cav_0", "cav_0"]}, "twice"),
    ({"kind": "erase", "count": 5}, r"attack.count=5 would make every one of the 5 agents"),
])
def test_bad_attackers_are_refused_naming_the_field(attack, match):
    with pytest.raises(ConfigError, match=match):
        roco_env.parallel_env(SCENE, **{f"attack.{k}": v for k, v in attack.items()})


@pytest.mark.parametrize("attack, match", [
    ({"kind": "pose_spoof", "params": {"n_ghost": 3}},
     r"unknown key 'attack.params.n_ghost'.*a parameter of attack.kind 'ghost'"),
    ({"kind": "ghost", "params": {"n_ghost": -1}}, r"attack.params.n_ghost=-1 is out of range"),
    ({"kind": "ghost", "params": {"placement": "sky"}}, r"attack.params.placement='sky'"),
    ({"kind": "erase", "params": {"objects": ["a"]}}, r"attack.params.objects must be a list"),
    ({"kind": "lie"}, r"attack.kind='lie' is not allowed"),
])
def test_bad_attack_parameters_are_refused_naming_the_field(attack, match):
    with pytest.raises(ConfigError, match=match):
        roco_env.parallel_env(SCENE, **{f"attack.{k}": v for k, v in attack.items()})


def test_attacks_never_tamper_with_what_attackers_send_each_other():
    _, clean = frame()
    _, attacked = frame(kind="pose_spoof", agents=["cav_0", "cav_1"], params={"offset_m": 9.0})
    for attacker in (0, 1):
        view = attacked.views[attacker]
        for slot in attacked_slots(view, 1 - attacker):
            assert np.array_equal(view.collab_poses[slot], clean.views[attacker].collab_poses[slot])
    moved = se2_relative(attacked.views[2].pose, attacked.views[2].collab_poses)
    assert np.allclose(moved, attacked.views[2].reported_relative)


def test_the_aliasing_pattern_makes_roco_pick_the_wrong_hypothesis():
    from roco_env.policies import make_policy

    env = roco_env.parallel_env(SCENE, max_cycles=1, **NOISE, **{
        "attack.kind": "ghost", "attack.agents": ["cav_1"],
        "attack.params": {"n_ghost": 20, "placement": "aliasing", "shift_m": 3.0}})
    observations, infos = env.reset(seed=0)
    delta = offset_pose(3.0, 0.0, 0.0)
    view = env._frame.views[0]
    (slot,) = attacked_slots(view, 1)
    action = make_policy("roco")(observations["cav_0"], infos["cav_0"])
    corrected = se2_compose(action[slot].astype(float), view.reported_relative[slot])
    wrong = se2_compose(delta, view.reported_relative[slot])  # where the ghosts fit
    assert np.hypot(*(corrected - wrong)[:2]) < 0.5  # the lie, not the truth, is matched
    assert np.hypot(*(corrected - view.true_relative[slot])[:2]) > 2.0


def adversarial(**params):
    from roco_env.attacks.adversarial_env import AdversarialEnv

    return AdversarialEnv(roco_env.parallel_env(SCENE, max_cycles=3, cavs=2, rsus=1, **{
        "attack.kind": "learned", "attack.params": {"ghosts": 2, **params}}))


def test_a_learned_attacker_is_a_pettingzoo_agent_that_passes_the_api_and_seed_tests():
    from pettingzoo.test import parallel_api_test, parallel_seed_test

    env = adversarial()
    assert env.possible_agents == ["cav_0", "cav_1", "rsu_0", "attacker_0"]
    assert env.action_space("attacker_0").shape == (3 + 3 * 2,)
    parallel_api_test(adversarial(), num_cycles=5)
    parallel_seed_test(adversarial)


def test_the_learned_attackers_action_shapes_the_next_frame_within_its_budget():
    env = adversarial(budget_m=2.0, budget_deg=1.0, consistent=False)
    observations, infos = env.reset(seed=3)
    vehicle = env.possible_agents.index(infos["attacker_0"]["privileged"]["vehicle"])
    victim = next(k for k in range(3) if k != vehicle)
    zeros = {a: np.zeros(env.action_space(a).shape) for a in env.possible_agents}
    before = env.env._frame.views[victim]
    (slot,) = attacked_slots(before, vehicle)  # no action yet: no lie
    assert np.array_equal(before.collab_poses[slot], env.env._frame.reported_poses[vehicle])
    lie = np.array([1.0, 1.0, -1.0, 0.5, 0.0, 1.0, 0.0, 0.0, -1.0])  # one ghost on, one off
    env.step({**zeros, "attacker_0": lie})
    after = env.env._frame.views[victim]
    (slot,) = attacked_slots(after, vehicle)
    shift = np.array([np.sqrt(2.0), np.sqrt(2.0), np.radians(-1.0)])  # clipped to the disc
    expected = se2_compose(env.env._frame.reported_poses[vehicle], shift)
    assert np.allclose(after.collab_poses[slot], expected)
    assert after.collab_object_ids[slot][-1] == -1  # the one ghost switched on
    assert np.allclose(after.collab_boxes[slot][-1, :2], [0.5 * 40.0, 0.0])


def test_the_learned_attackers_reward_is_minus_its_victims_ap_and_its_detection():
    env = adversarial(detection_penalty=2.0)
    observations, infos = env.reset(seed=0)
    zeros = {a: np.zeros(env.action_space(a).shape) for a in env.possible_agents}
    _, rewards, _, _, infos = env.step(zeros)
    vehicle = infos["attacker_0"]["privileged"]["vehicle"]
    victims = [a for a in ("cav_0", "cav_1", "rsu_0") if a != vehicle]
    assert rewards["attacker_0"] == pytest.approx(
        -np.mean([max(infos[a]["ap70"], 0.0) for a in victims]))
    rejected = {a: dict(info) for a, info in infos.items() if a in victims}
    for info in rejected.values():
        info["rejected"] = np.array([s == vehicle for s in info["evaluated_collaborators"]])
    assert env.attack.reward(0, rejected) == pytest.approx(rewards["attacker_0"] - 2.0)


@pytest.mark.parametrize("params, match", [
    ({"budget_m": -1.0}, r"attack.params.budget_m=-1.0 is out of range; allowed \[0.0, 100.0\]"),
    ({"ghosts": -2}, r"attack.params.ghosts=-2 is out of range"),
    ({"target": "cav_7"}, r"attack.params.target='cav_7' must be an honest agent"),
])
def test_a_bad_learned_attack_budget_or_target_is_refused(params, match):
    with pytest.raises(ConfigError, match=match):
        adversarial(**params)


def test_the_adversarial_env_needs_a_learned_attack_and_checks_the_attackers_action():
    from roco_env.attacks.adversarial_env import AdversarialEnv

    with pytest.raises(ValueError, match="attack.kind='learned'"):
        AdversarialEnv(roco_env.parallel_env(SCENE, max_cycles=2))
    env = adversarial()
    env.reset(seed=0)
    zeros = {a: np.zeros(env.action_space(a).shape) for a in env.possible_agents}
    with pytest.raises(ValueError, match="action of attacker_0 must be 9 finite numbers"):
        env.step({**zeros, "attacker_0": np.full(9, np.nan)})
