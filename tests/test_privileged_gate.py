"""``privileged_gate``: the perfect rejection (the attackers, read from the privileged
truth) behind a base aligner in gate mode, the reference row of the attack protocol."""

from __future__ import annotations

import numpy as np
import pytest

import roco_env
from roco_env.policies import make_policy
from roco_env.policies.spec import merge_env_overrides

SPOOF = {"attack.kind": "pose_spoof", "attack.agents": ["cav_1"],
         "attack.params": {"offset_m": 10.0}}


def test_it_acts_in_gate_mode_behind_its_base():
    assert make_policy("privileged_gate", base="coalign").env_overrides == {
        "action.mode": "gate", "action.base": "coalign"}


def test_it_rejects_exactly_the_attacker_from_the_first_step():
    policy = make_policy("privileged_gate")
    env = roco_env.parallel_env("urban_intersection", max_cycles=3, sigma_t=0.4, sigma_r=0.4,
                                **merge_env_overrides(SPOOF, policy))
    observations, infos = env.reset(seed=0)
    rejected = 0
    while env.agents:
        observations, _, _, _, infos = env.step(
            {a: policy(observations[a], infos[a]) for a in env.agents})
        for agent, info in infos.items():
            senders = info["evaluated_collaborators"]
            assert info["rejected"][: len(senders)].tolist() == [
                agent != "cav_1" and s == "cav_1" for s in senders]
            rejected += int(info["rejected"].sum())
    assert rejected >= 3 * 4 - 3  # every honest ego that hears cav_1, every step


def test_without_the_privileged_truth_it_says_what_it_needs():
    policy = make_policy("privileged_gate")
    env = roco_env.parallel_env("urban_intersection", max_cycles=1, privileged=False,
                                **merge_env_overrides(SPOOF, policy))
    observations, infos = env.reset(seed=0)
    with pytest.raises(ValueError, match=r"info\['privileged'\]\['collab_attackers'\]"):
        policy(observations["cav_0"], infos["cav_0"])


@pytest.mark.parametrize("base, match", [
    ("defend", "base must be the policy spec of an aligner"),
    ("privileged_gate", "base must be the policy spec of an aligner"),
])
def test_a_gate_as_its_base_is_refused(base, match):
    with pytest.raises(ValueError, match=match):
        make_policy("privileged_gate", base=base)


def test_empty_slots_are_never_rejected():
    policy = make_policy("privileged_gate")
    observation = {"collab_mask": np.array([1, 0, 0], np.int8)}
    info = {"privileged": {"collab_attackers": np.array([True, True, False])}}
    assert policy(observation, info).tolist() == [1, 0, 0]
