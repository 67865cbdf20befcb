"""FlattenActions: flat (3N,) actions reach the env as the same (N, 3) corrections."""

from __future__ import annotations

import numpy as np
import pytest

import roco_env
from roco_env.wrappers import FlattenActions

FAST = dict(scenario="urban_intersection", density=1.5, max_boxes=24, sigma_t=0.4, sigma_r=0.4)


def test_flat_actions_step_like_the_reshaped_ones():
    plain = roco_env.parallel_env(max_cycles=3, **FAST)
    flat = FlattenActions(roco_env.parallel_env(max_cycles=3, **FAST))
    n = plain.config.max_collaborators
    assert flat.action_space("cav_0").shape == (3 * n,)
    plain.reset(seed=4)
    flat.reset(seed=4)
    rng = np.random.default_rng(0)
    actions = {a: rng.normal(0, 0.3, (n, 3)).astype(np.float32) for a in plain.agents}
    _, rewards_plain, _, _, infos_plain = plain.step(actions)
    _, rewards_flat, _, _, infos_flat = flat.step({a: v.reshape(-1) for a, v in actions.items()})
    assert rewards_plain == rewards_flat
    for agent in plain.possible_agents:
        np.testing.assert_array_equal(infos_plain[agent]["rpe_after"],
                                      infos_flat[agent]["rpe_after"])


def test_flat_action_of_wrong_length_is_rejected_by_name():
    env = FlattenActions(roco_env.parallel_env(max_cycles=3, **FAST))
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"action of 'cav_0' must have shape \(15,\)"):
        env.step({a: np.zeros(7, dtype=np.float32) for a in env.agents})
