"""``reject_untested``: in select mode with its base aligner as the one choice, reject
exactly the filled slots the aligner computed no do-no-harm statistic for."""

from __future__ import annotations

import numpy as np
import pytest

import roco_env
from roco_env.observation_modes import DIAGNOSTICS
from roco_env.policies import make_policy
from roco_env.policies.reject_untested import NO_STATISTIC, STATISTIC
from roco_env.policies.spec import merge_env_overrides


def test_it_acts_in_select_mode_on_the_aligned_observation_with_its_base():
    assert make_policy("reject_untested").env_overrides == {
        "action.mode": "select", "action.choices": ["roco_antialias"],
        "action.base": "roco_antialias", "observation.mode": "aligned"}
    assert make_policy("reject_untested", base="roco").env_overrides["action.base"] == "roco"


def urban_episode(policy):
    """(action, filled, untested, rejected) of every agent's step of a two-step
    urban_intersection episode at 3 m / 3 deg, seed 0, where ``policy`` acts."""
    env = roco_env.parallel_env("urban_intersection", max_cycles=2, sigma_t=3.0, sigma_r=3.0,
                                **merge_env_overrides({}, policy))
    observations, infos = env.reset(seed=0)
    rows = []
    while env.agents:
        actions = {a: policy(observations[a], infos[a]) for a in env.agents}
        slots = {a: (observations[a]["collab_mask"] > 0,
                     observations[a]["diagnostics"][:, STATISTIC] == NO_STATISTIC)
                 for a in actions}
        observations, _, _, _, infos = env.step(actions)
        rows += [(actions[a], *slots[a], infos[a]["rejected"]) for a in actions]
    return rows


def test_it_rejects_exactly_the_untested_collaborators_in_an_episode():
    """urban_intersection at 3 m / 3 deg, seed 0: roco_antialias leaves 1 of 40 slots
    untested over two steps; that one, and only it, is rejected by the env."""
    untested = tested = 0
    for action, filled, blind, rejected in urban_episode(make_policy("reject_untested")):
        np.testing.assert_array_equal(action, (filled & blind).astype(np.int64))
        np.testing.assert_array_equal(rejected, action > 0)
        untested += int((filled & blind).sum())
        tested += int((filled & ~blind).sum())
    assert untested >= 1 and tested >= 30


def test_empty_slots_are_never_rejected():
    policy = make_policy("reject_untested")
    diagnostics = np.zeros((3, len(DIAGNOSTICS)), np.float32)
    diagnostics[:, STATISTIC] = [NO_STATISTIC, 2.5, NO_STATISTIC]
    action = policy({"collab_mask": np.array([1, 1, 0], np.int8), "diagnostics": diagnostics})
    np.testing.assert_array_equal(action, [1, 0, 0])


@pytest.mark.parametrize("base", ["defend", "privileged_gate", "reject_untested", ""])
def test_a_gate_or_nothing_as_its_base_is_refused(base):
    with pytest.raises(ValueError, match="reject_untested: base must be the policy spec of "
                                         "an aligner"):
        make_policy("reject_untested", base=base)


def test_without_the_aligned_observation_it_says_what_it_needs():
    with pytest.raises(ValueError, match="observation.mode='aligned'"):
        make_policy("reject_untested")({"collab_mask": np.ones(2, np.int8)})


def test_the_shipped_learned_select_takes_exactly_its_actions():
    """The docs say learned_select's guard is this rule and its network adds nothing
    measurable (baselines/learned_select/README.md): on a seeded episode where a slot is
    rejected, its actions (choice 3 = roco_antialias, 4 = reject) are this policy's (0, 1).
    A retrained network that deviates fails here, and the docs must say what it adds."""
    actions = {}
    for name in ("reject_untested", "learned_select"):
        policy = make_policy(name)
        env = roco_env.parallel_env("urban_intersection", max_cycles=2, sigma_t=3.0,
                                    sigma_r=3.0, **merge_env_overrides({}, policy))
        observations, infos = env.reset(seed=0)
        taken = actions[name] = []
        while env.agents:
            step = {a: policy(observations[a], infos[a]) for a in env.agents}
            taken.append(step)
            observations, _, _, _, infos = env.step(step)
    rejected = 0
    for rule, learned in zip(actions["reject_untested"], actions["learned_select"], strict=True):
        for agent, action in rule.items():
            np.testing.assert_array_equal(np.where(learned[agent] == 4, 1, 0), action)
            assert set(np.unique(learned[agent])) <= {3, 4}
            rejected += int(action.sum())
    assert rejected >= 1


def test_tested_and_untested_name_the_choices_each_kind_of_slot_takes():
    """``untested=roco_fallback``: choices [roco_antialias, roco_fallback], untested slots
    take 1 and none is rejected; ``tested=roco_fallback``: tested slots take 1, untested
    ones reject (2); the diagnostics that decide stay the base's."""
    diagnostics = np.zeros((3, len(DIAGNOSTICS)), np.float32)
    diagnostics[:, STATISTIC] = [NO_STATISTIC, 2.5, NO_STATISTIC]
    observation = {"collab_mask": np.array([1, 1, 0], np.int8), "diagnostics": diagnostics}
    fallback = make_policy("reject_untested", untested="roco_fallback")
    assert fallback.env_overrides["action.choices"] == ["roco_antialias", "roco_fallback"]
    assert fallback.env_overrides["action.base"] == "roco_antialias"
    np.testing.assert_array_equal(fallback(observation), [1, 0, 0])
    refined = make_policy("reject_untested", tested="roco_fallback")
    assert refined.env_overrides["action.choices"] == ["roco_antialias", "roco_fallback"]
    np.testing.assert_array_equal(refined(observation), [2, 1, 1])
    both = make_policy("reject_untested", tested="roco_fallback", untested="roco_fallback")
    np.testing.assert_array_equal(both(observation), [1, 1, 1])


@pytest.mark.parametrize("params, field", [
    ({"tested": "reject"}, "tested must be"),
    ({"untested": "defend"}, "untested .or 'reject'. must be"),
    ({"untested": ""}, "untested .or 'reject'. must be"),
    ({"untested": "nonesuch"}, "untested .or 'reject'. must be .*unknown policy"),
    ({"untested": "roco:nope=1"}, "untested .or 'reject'. must be .*nope"),
    ({"untested": "learned_select"}, "untested .*action.mode 'select'"),
    ({"tested": "reject_untested"}, "tested must be .*action.mode 'select'"),
    ({"tested": "privileged_gate"}, "tested must be .*action.mode 'gate'"),
    ({"base": "nonesuch"}, "base must be .*unknown policy"),
    ({"tested": "roco_fallback", "tested_within_m": 20.0}, r"tested_within_m.*\[0.0, 20.0\)"),
])
def test_a_tested_or_untested_that_is_no_aligner_is_refused(params, field):
    """Each field is checked against the registry when the policy is built (not at env
    build), and the error names the field and what it allows."""
    with pytest.raises(ValueError, match=field):
        make_policy("reject_untested", **params)


def test_with_untested_roco_fallback_the_env_fuses_every_collaborator():
    """urban_intersection at 3 m / 3 deg, seed 0 (one untested slot, above): that slot
    takes roco_fallback's pose (choice 1), the others roco_antialias's; nothing rejected."""
    fallen_back = 0
    policy = make_policy("reject_untested", untested="roco_fallback")
    for action, filled, blind, rejected in urban_episode(policy):
        np.testing.assert_array_equal(action, (filled & blind).astype(np.int64))
        assert not np.any(rejected)
        fallen_back += int((filled & blind).sum())
    assert fallen_back >= 1


def test_tested_within_m_takes_the_tested_choice_only_near_the_base_pose():
    """Slot 0 tested, roco_fallback 0.1 m from roco_antialias: roco_fallback (1); slot 1
    tested, 2.5 m apart (a stall's alias): roco_antialias (0); slot 2 untested: reject."""
    from roco_env.observation_modes import CHOICE_DIAGNOSTICS
    from roco_env.policies.reject_untested import GAP_M

    assert CHOICE_DIAGNOSTICS[GAP_M][0] == "gap_m"
    diagnostics = np.zeros((3, len(DIAGNOSTICS)), np.float32)
    diagnostics[:, STATISTIC] = [2.0, 2.5, NO_STATISTIC]
    choice = np.zeros((3, 2, len(CHOICE_DIAGNOSTICS)), np.float32)
    choice[:, 1, GAP_M] = [0.1, 2.5, 0.0]
    policy = make_policy("reject_untested", tested="roco_fallback", tested_within_m=0.5)
    action = policy({"collab_mask": np.ones(3, np.int8), "diagnostics": diagnostics,
                     "choice_diagnostics": choice})
    np.testing.assert_array_equal(action, [1, 0, 2])
    with pytest.raises(ValueError, match="tested_within_m needs tested other than base"):
        make_policy("reject_untested", tested_within_m=0.5)
