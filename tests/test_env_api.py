"""PettingZoo / Gymnasium / SuperSuit / RLlib API conformance of the environment."""

from __future__ import annotations

import types
from functools import partial

import gymnasium
import numpy as np
import pettingzoo
import pytest
from conftest import run_python
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import (
    api_test,
    max_cycles_test,
    parallel_api_test,
    parallel_seed_test,
    render_test,
)
from pettingzoo.utils.conversions import parallel_to_aec

import roco_env
from roco_env.env import CollabPerceptionEnv
from roco_env.wrappers import EgoEnv, FlattenObservations

# Small, fast settings (5 agents, ~30 vehicles) used throughout.
FAST = dict(scenario="urban_intersection", density=1.5, max_boxes=24)
# Two agents that always see each other (small and fast).
TINY = dict(scenario="v2x_crossroad", density=1.5, max_boxes=24, max_collaborators=1)


def fast_parallel(**kwargs):
    return roco_env.parallel_env(**{**FAST, **kwargs})


def fast_aec(**kwargs):
    return roco_env.env(**{**FAST, **kwargs})


def test_parallel_api_test():
    parallel_api_test(fast_parallel(), num_cycles=12)


def test_aec_api_test():
    api_test(parallel_to_aec(fast_parallel(max_cycles=6)), num_cycles=8)


def test_parallel_seed_test():
    parallel_seed_test(lambda: roco_env.parallel_env(**TINY, max_cycles=6), num_cycles=6)


def test_max_cycles_test():
    max_cycles_test(types.SimpleNamespace(parallel_env=fast_parallel, env=fast_aec))


def test_render_test():
    render_test(fast_parallel_aec_for_render)


def fast_parallel_aec_for_render(render_mode=None):
    return fast_aec(render_mode=render_mode)


def test_module_level_constructors():
    aec = roco_env.env(**FAST, max_cycles=2)
    assert isinstance(aec, pettingzoo.AECEnv)
    assert isinstance(aec.unwrapped, CollabPerceptionEnv)
    assert "urban_intersection" in roco_env.list_scenarios()


def test_users_calls_still_work_whichever_module_loads_the_env_first():
    """``roco_env.env(...)`` is PettingZoo's AEC constructor whichever module imported
    roco_env/env.py first; ``roco_env.env`` is that module (callable)."""
    probe = ("import sys, roco_env; light = 'roco_env.pipeline' not in sys.modules; "
             "from roco_env.wrappers import EgoEnv; "
             "aec = roco_env.env('v2x_crossroad', max_cycles=2); "
             "from roco_env.env import CollabPerceptionEnv, aec_env, parallel_env; "
             "par = roco_env.parallel_env('v2x_crossroad'); "
             "print(light, roco_env.env is sys.modules['roco_env.env'], "
             "roco_env.parallel_env is parallel_env, "
             "roco_env.CollabPerceptionEnv is CollabPerceptionEnv, "
             "isinstance(aec.unwrapped, CollabPerceptionEnv), type(par).__name__, "
             "par.max_cycles)")
    assert run_python(probe) == "True True True True True CollabPerceptionEnv 100"


def test_the_environment_module_is_a_module_and_import_roco_env_stays_light():
    """``import roco_env`` loads neither the pipeline nor torch; the environment's module
    is an ordinary module (``import ... as``, ``pydoc.locate``)."""
    probe = ("import sys, pydoc, types, roco_env; "
             "light = not {'roco_env.pipeline', 'roco_env.env', 'torch'} & set(sys.modules); "
             "import roco_env.env as m; "
             "print(light, isinstance(m, types.ModuleType), "
             "m.CollabPerceptionEnv is roco_env.CollabPerceptionEnv, "
             "pydoc.locate('roco_env.env.CollabPerceptionEnv') is m.CollabPerceptionEnv, "
             "roco_env.env is m, callable(roco_env.env))")
    assert run_python(probe) == "True True True True True True"


def test_the_environment_module_can_be_monkeypatched_by_name(monkeypatch):
    import roco_env.env

    monkeypatch.setattr("roco_env.env.DEFAULT_MAX_CYCLES", 7)
    assert roco_env.env.DEFAULT_MAX_CYCLES == 7


def test_pettingzoo_registry():
    par = pettingzoo.make("parallel", roco_env.ENV_ID, **TINY, max_cycles=3)
    assert isinstance(par, CollabPerceptionEnv) and par.max_cycles == 3
    aec = pettingzoo.make("aec", roco_env.ENV_ID, **TINY)
    assert isinstance(aec, pettingzoo.AECEnv) and aec.unwrapped.max_cycles == 100


def test_metadata_spaces_and_agents():
    env = fast_parallel()
    assert env.metadata["render_modes"] == ["rgb_array", "human"]
    assert env.metadata["is_parallelizable"] is True
    assert env.metadata["render_fps"] == 10
    assert env.metadata["name"] == roco_env.ENV_ID == "roco/CollabPerception-v0"
    assert env.possible_agents == ["cav_0", "cav_1", "cav_2", "cav_3", "rsu_0"]
    for agent in env.possible_agents:
        assert env.observation_space(agent) is env.observation_space(agent)
        assert env.action_space(agent).shape == (5, 3)
    assert env.observation_space("cav_0") is not env.observation_space("cav_1")
    obs, infos = env.reset(seed=1)
    for agent in env.possible_agents:
        assert obs[agent] in env.observation_space(agent)
        assert set(infos[agent]) == {"evaluated", "agent", "collaborators", "n_collaborators",
                                     "privileged"}
        assert infos[agent]["agent"] == agent
    for _ in range(3):  # agents stay constant until truncation
        obs, *_ = env.step({a: np.zeros((5, 3)) for a in env.agents})
        assert env.agents == env.possible_agents


def test_observation_layout_matches_contract():
    env = fast_parallel(max_boxes=24, max_collaborators=5)
    obs, infos = env.reset(seed=1)
    o, info = obs["cav_0"], infos["cav_0"]
    shapes = {key: value.shape for key, value in o.items()}
    assert shapes == {
        "pose": (3,), "boxes": (24, 7), "uncertainty": (24, 3), "scores": (24,),
        "box_mask": (24,), "collab_mask": (5,), "collab_poses": (5, 3),
        "collab_rel_poses": (5, 3), "collab_boxes": (5, 24, 7),
        "collab_uncertainty": (5, 24, 3), "collab_scores": (5, 24),
        "collab_box_mask": (5, 24),
    }
    filled = int(o["collab_mask"].sum())
    assert filled == info["n_collaborators"] == len(info["collaborators"]) >= 1
    np.testing.assert_allclose(o["collab_rel_poses"][:filled],
                               info["privileged"]["reported_relative_poses"][:filled], atol=1e-4)
    assert not o["collab_mask"][filled:].any() and not o["collab_boxes"][filled:].any()
    n_boxes = int(o["box_mask"].sum())
    assert np.all(o["scores"][n_boxes:] == 0) and np.all(o["scores"][:n_boxes] > 0)
    assert info["privileged"]["true_relative_poses"].dtype == np.float64


def test_ego_env_passes_gymnasium_check_env():
    check_env(EgoEnv(**TINY, max_cycles=5), skip_render_check=True)


def test_ego_env_controls_one_agent_and_renders():
    ego = EgoEnv(**TINY, max_cycles=2, render_mode="rgb_array", agent="rsu_0")
    obs, info = ego.reset(seed=0)
    assert obs in ego.observation_space and info["collaborators"] == ["cav_0"]
    obs, reward, terminated, truncated, info = ego.step(ego.action_space.sample())
    assert isinstance(reward, float) and not terminated and not truncated
    image = ego.render()
    assert image.shape[2] == 3 and len(np.unique(image.reshape(-1, 3), axis=0)) > 10
    *_, truncated, _ = ego.step(np.zeros((1, 3), dtype=np.float32))
    assert truncated


def test_ego_env_gymnasium_registry():
    env = gymnasium.make(roco_env.EGO_ENV_ID, **TINY, max_cycles=2)
    obs, _ = env.reset(seed=0)
    assert obs in env.observation_space


def test_supersuit_pad_and_flatten_construct_and_step():
    supersuit = pytest.importorskip("supersuit")
    # SuperSuit's observation wrappers accept Box spaces only: flatten the Dict first.
    env = supersuit.flatten_v0(supersuit.pad_observations_v0(FlattenObservations(
        fast_parallel(max_cycles=3))))
    obs, _ = env.reset(seed=0)
    space = env.observation_space("cav_0")
    assert isinstance(space, gymnasium.spaces.Box) and space.shape == obs["cav_0"].shape
    dict_space = fast_parallel().observation_space("cav_0")
    assert space.shape == (gymnasium.spaces.flatdim(dict_space),)
    obs, rewards, *_ = env.step({a: env.action_space(a).sample() for a in env.agents})
    assert obs["cav_0"] in space and set(rewards) == set(env.possible_agents)


def test_rllib_parallel_pettingzoo_env():
    module = pytest.importorskip("ray.rllib.env.wrappers.pettingzoo_env",
                                 reason="ray[rllib] is not importable here")
    env = module.ParallelPettingZooEnv(fast_parallel(max_cycles=3))
    obs, _ = env.reset(seed=0)
    obs, rewards, *_ = env.step({a: np.zeros((5, 3), dtype=np.float32) for a in obs})
    assert set(rewards) == set(obs)


def test_partial_constructor_keeps_overrides():
    make = partial(roco_env.parallel_env, **FAST)
    assert make(sigma_t=0.4).config.noise.sigma_t == 0.4
