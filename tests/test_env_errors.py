"""Bad input to the environment and its policies: clear ValueErrors naming the culprit."""

from __future__ import annotations

import numpy as np
import pytest

import roco_env
from roco_env.evaluation import filled_rpe_rows
from roco_env.policies import make_policy
from roco_env.wrappers import EgoEnv

FAST = dict(scenario="urban_intersection", density=1.5, max_boxes=24)


@pytest.fixture
def env():
    env = roco_env.parallel_env(**FAST, max_cycles=2)
    env.reset(seed=0)
    return env


def zeros(env):
    return {a: np.zeros((5, 3)) for a in env.agents}


def test_action_of_wrong_shape(env):
    actions = zeros(env)
    actions["cav_2"] = np.zeros((4, 3))
    with pytest.raises(ValueError, match=r"'cav_2'.*shape \(5, 3\).*got \(4, 3\)"):
        env.step(actions)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_action(env, bad):
    actions = zeros(env)
    actions["rsu_0"][1, 2] = bad
    with pytest.raises(ValueError, match="'rsu_0' contains NaN or inf"):
        env.step(actions)


def test_non_numeric_action(env):
    actions = zeros(env)
    actions["cav_0"] = "left"
    with pytest.raises(ValueError, match="'cav_0' must be an array of real numbers"):
        env.step(actions)


def test_unknown_and_missing_agent_keys(env):
    with pytest.raises(ValueError, match=r"unknown agent key\(s\) \['cav_9'\]"):
        env.step({**zeros(env), "cav_9": np.zeros((5, 3))})
    actions = zeros(env)
    del actions["cav_1"]
    with pytest.raises(ValueError, match=r"missing agent\(s\) \['cav_1'\]"):
        env.step(actions)
    with pytest.raises(ValueError, match="actions must be a dict"):
        env.step([np.zeros((5, 3))])
    with pytest.raises(ValueError, match="unknown agent 'car_0'"):
        env.observation_space("car_0")


def test_step_after_the_episode_ended(env):
    for _ in range(2):
        env.step(zeros(env))
    assert env.agents == []
    with pytest.raises(ValueError, match="episode ended"):
        env.step({"cav_0": np.zeros((5, 3))})
    env.reset(seed=0)
    env.step(zeros(env))  # usable again after reset


def test_step_before_reset():
    env = roco_env.parallel_env(**FAST)
    with pytest.raises(ValueError, match="reset"):
        env.step({})


def test_bad_constructor_arguments():
    with pytest.raises(ValueError, match="unknown key 'sigma_x'"):
        roco_env.parallel_env(**FAST, sigma_x=0.3)
    with pytest.raises(ValueError, match="noise.sigma_t=-1.0 is out of range"):
        roco_env.parallel_env(**FAST, sigma_t=-1.0)
    with pytest.raises(ValueError, match="unknown scenario 'nowhere'"):
        roco_env.parallel_env("nowhere")
    with pytest.raises(ValueError, match="render_mode must be None or one of"):
        roco_env.parallel_env(**FAST, render_mode="ansi")
    with pytest.raises(ValueError, match="max_cycles must be an integer >= 1"):
        roco_env.parallel_env(**FAST, max_cycles=0)
    with pytest.raises(ValueError, match="agents.evaluated must be a non-empty list"):
        roco_env.parallel_env(**FAST, **{"agents.evaluated": ["cav_7"]})
    with pytest.raises(ValueError, match="needs detector.preset='learned'.*got detector.preset="
                                         "'realistic'"):
        roco_env.parallel_env(**FAST, fusion="intermediate")
    with pytest.raises(ValueError, match="needs detector.preset='learned'.*'ideal'"):
        roco_env.parallel_env(**FAST, fusion="intermediate", detector="ideal", features=True)


@pytest.mark.parametrize("seed", [-1, 1.5, "0", True])
def test_bad_reset_seed_names_the_argument(env, seed):
    with pytest.raises(ValueError, match=f"seed must be None or an integer >= 0; got {seed!r}"):
        env.reset(seed=seed)
    env.reset(seed=np.int64(3))  # numpy integers are seeds too


def test_oracle_without_info(env):
    obs, infos = env.reset(seed=0)
    oracle = make_policy("oracle")
    with pytest.raises(ValueError, match="oracle policy needs the env's info"):
        oracle(obs["cav_0"])
    with pytest.raises(ValueError, match="oracle policy needs the env's info"):
        oracle(obs["cav_0"], {"collaborators": []})
    assert oracle(obs["cav_0"], infos["cav_0"]).shape == (5, 3)
    with pytest.raises(ValueError, match="'collab_mask'"):
        make_policy("identity")({"pose": np.zeros(3)})


def test_ego_env_bad_arguments():
    with pytest.raises(ValueError, match="agent must be one of"):
        EgoEnv(**FAST, agent="cav_8")
    with pytest.raises(ValueError, match=r"others must be a policy\(obs, info\) -> action; "
                                         "got 3"):
        EgoEnv(**FAST, others=3)
    with pytest.raises(ValueError, match="unknown policy 'rocco'"):
        EgoEnv(**FAST, others="rocco")
    ego = EgoEnv(**FAST)
    with pytest.raises(ValueError, match="before reset"):
        ego.step(np.zeros((5, 3)))


def test_ego_env_others_by_policy_name():
    ego = EgoEnv(**FAST, max_cycles=1, others="oracle")
    ego.reset(seed=0)
    ego.step(np.zeros((5, 3)))
    others = [info for agent, info in ego._last[1].items() if agent != ego.agent]
    assert others and all(np.allclose(filled_rpe_rows(i["rpe_after"]), 0, atol=1e-6)
                          and filled_rpe_rows(i["rpe_before"]).max() > 0.01 for i in others)


def test_ego_env_resets_a_stateful_others_policy_with_each_episode():
    class Counting:
        resets = 0

        def __call__(self, observation, info=None):
            return np.zeros((observation["collab_mask"].shape[0], 3), dtype=np.float32)

        def reset(self):
            self.resets += 1

    others = Counting()
    ego = EgoEnv(**FAST, max_cycles=1, others=others)
    for seed in (0, 1):
        ego.reset(seed=seed)
    assert others.resets == 2


def test_render_without_mode_or_before_reset():
    env = roco_env.parallel_env(**FAST)
    with pytest.warns(UserWarning, match="without a render_mode"):
        assert env.render() is None
    env = roco_env.parallel_env(**FAST, render_mode="rgb_array")
    with pytest.raises(ValueError, match="before reset"):
        env.render()


def test_aec_nan_action_raises_at_the_offending_agents_own_step():
    aec = roco_env.env("v2x_crossroad", density=1.5, max_boxes=24, max_cycles=4)
    aec.reset(seed=0)
    first = aec.agent_selection
    shape = aec.action_space(first).shape
    bad = np.full(shape, np.nan)
    with pytest.raises(ValueError, match=f"action for agent '{first}' contains NaN"):
        aec.step(bad)
    assert aec.agent_selection == first  # nothing stored, still its turn
    for _ in range(2 * len(aec.possible_agents)):  # two full cycles of valid actions
        aec.step(np.zeros(aec.action_space(aec.agent_selection).shape))
    with pytest.raises(ValueError, match="must have shape"):
        aec.step(np.zeros(3))
