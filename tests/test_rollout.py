"""The Policy protocol and the one episode loop: every policy is one, plain functions still
act, and the env is the only place an action is checked."""

from __future__ import annotations

import numpy as np
import pytest

import roco_env
from roco_env.action_modes import CorrectionMode
from roco_env.policies import available_policies, make_policy
from roco_env.policies.base import AlignmentResult, Policy, PolicyAdapter, act, as_policy
from roco_env.rollout import play_episode
from roco_env.sweeps.cells import Cell
from roco_env.sweeps.episode import run_episode

SMALL = dict(scenario="crowded_intersection", cavs=2, rsus=1, max_boxes=24)


def _zeros(observation, info=None):
    """A user policy as a plain function: trust every reported pose."""
    return np.zeros((len(observation["collab_mask"]), 3), dtype=np.float32)


@pytest.mark.parametrize("name", sorted(set(available_policies()) - {"learned_select"}))
def test_every_registered_policy_is_a_policy_of_its_own(name):
    policy = make_policy(name)
    assert isinstance(policy, Policy) and not isinstance(policy, PolicyAdapter)


def test_a_plain_function_gets_the_defaults():
    policy = as_policy(_zeros)
    assert isinstance(policy, PolicyAdapter) and isinstance(policy, Policy)
    assert not policy.keeps_state and policy.last_result is None and policy.env_overrides is None
    policy.reset()  # nothing to forget, no error
    assert policy.input_files() == ()
    assert as_policy(policy) is policy
    with pytest.raises(ValueError, match=r"others must be a policy\(obs, info\) -> action; got 3"):
        as_policy(3, "others")


def test_an_object_with_some_members_keeps_them():
    class Counting:
        keeps_state = "a call count"

        def __init__(self):
            self.resets = 0

        def __call__(self, observation, info=None):
            return _zeros(observation)

        def reset(self):
            self.resets += 1

    inner = Counting()
    policy = as_policy(inner)  # no last_result: adapted
    assert policy.keeps_state == "a call count"
    policy.reset()
    assert inner.resets == 1


def test_act_never_returns_a_stale_result():
    class Once:
        keeps_state = False
        last_result = None

        def __call__(self, observation, info=None):
            if self.last_result is None:
                self.last_result = AlignmentResult(np.zeros((1, 3)), np.ones(1, bool))
            return np.zeros((1, 3))

        def reset(self):
            self.last_result = None

    policy = Once()
    _, first = act(policy, {}, None)
    _, second = act(policy, {}, None)
    assert first is policy.last_result and second is None


def test_a_plain_function_plays_the_same_episode_as_the_identity_policy():
    def episode(policy):
        env = roco_env.parallel_env(**SMALL, max_cycles=3, sigma_t=0.5, sigma_r=0.5)
        steps = list(play_episode(env, dict.fromkeys(env.possible_agents, policy), seed=4))
        return [(s.number, s.rewards, s.infos["cav_0"]["fused_boxes"]) for s in steps]

    plain, identity = episode(_zeros), episode(make_policy("identity"))
    assert [number for number, _, _ in plain] == [1, 2, 3]
    for (_, rewards_a, boxes_a), (_, rewards_b, boxes_b) in zip(plain, identity, strict=True):
        assert rewards_a == rewards_b
        np.testing.assert_array_equal(boxes_a, boxes_b)


def test_the_loop_resets_each_policy_once_and_stops_at_max_steps():
    class Counting(PolicyAdapter):
        resets = 0

        def reset(self):
            type(self).resets += 1

    shared = Counting(_zeros)
    env = roco_env.parallel_env(**SMALL, max_cycles=10)
    steps = list(play_episode(env, dict.fromkeys(env.possible_agents, shared), max_steps=2))
    assert Counting.resets == 1 and len(steps) == 2 and env.agents  # not truncated yet
    turn = steps[0].turns["cav_0"]
    assert turn.result is None and turn.seconds >= 0 and turn.info["agent"] == "cav_0"
    np.testing.assert_array_equal(steps[0].actions["cav_0"], turn.action)


def test_a_missing_policy_names_the_agent():
    env = roco_env.parallel_env(**SMALL)
    with pytest.raises(ValueError, match=r"policies lacks agent\(s\) \['rsu_0'\]"):
        next(play_episode(env, {"cav_0": _zeros, "cav_1": _zeros}))


def test_the_env_checks_each_action_once(monkeypatch):
    calls = []
    check = CorrectionMode.check

    def counted(self, action, agent):
        calls.append(agent)
        return check(self, action, agent)

    monkeypatch.setattr(CorrectionMode, "check", counted)
    cell = Cell("crowded_intersection", 0.4, "identity", 0, 2, overrides=(("cavs", 2), ("rsus", 1)))
    metrics, _ = run_episode(cell)
    assert metrics["steps"] == 2
    assert sorted(calls) == sorted(["cav_0", "cav_1", "rsu_0"] * 2)


def test_a_bad_action_is_the_envs_error_naming_the_agent():
    def short(observation, info=None):
        return np.zeros((1, 3))

    env = roco_env.parallel_env(**SMALL)
    with pytest.raises(ValueError, match=r"action for agent 'cav_0' must have shape \(5, 3\)"):
        next(play_episode(env, dict.fromkeys(env.possible_agents, short)))
