"""PettingZoo and Gymnasium conformance on every shipped scenario with its own defaults.

Infos must compare equal under ``==`` (the seed tests do so), so they hold no NaN,
and have fixed shapes so Gymnasium's vector envs can stack them.
"""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pettingzoo.test import api_test, parallel_api_test, parallel_seed_test, seed_test
from test_replay import write_opv2v

import roco_env
from roco_env.evaluation import UNDEFINED, _padded, info_capacity

CYCLES = 3


@pytest.fixture(scope="module")
def replay_folder(tmp_path_factory):
    return write_opv2v(tmp_path_factory.mktemp("opv2v"))


def make_parallel(scenario, replay_folder, **kwargs):
    """The scenario with its defaults; the replay one gets the fixture folder it requires."""
    return roco_env.parallel_env(scenario, max_cycles=CYCLES,
                                 **replay_overrides(scenario, replay_folder), **kwargs)


def replay_overrides(scenario, replay_folder):
    """The fixture folder and its agent counts (2 CAVs, 1 RSU) for the replay scenario."""
    return {"traffic.path": str(replay_folder), "rsus": 1} if scenario == "opv2v_replay" else {}


def walk(value, path=""):
    """(path, leaf) of every leaf of a nested info."""
    if isinstance(value, dict):
        for key, item in value.items():
            yield from walk(item, f"{path}/{key}")
    else:
        yield path, value


SCENARIOS = roco_env.list_scenarios()


def test_every_shipped_scenario_is_covered():
    assert len(SCENARIOS) >= 9 and "opv2v_replay" in SCENARIOS


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_parallel_api_and_seed(scenario, replay_folder):
    parallel_api_test(make_parallel(scenario, replay_folder), num_cycles=CYCLES)
    parallel_seed_test(lambda: make_parallel(scenario, replay_folder), num_cycles=CYCLES)


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_aec_api_and_seed(scenario, replay_folder):
    def aec():
        return roco_env.env(**replay_overrides(scenario, replay_folder), scenario=scenario,
                            max_cycles=CYCLES)

    api_test(aec(), num_cycles=CYCLES)
    seed_test(aec, num_cycles=CYCLES)


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_infos_have_no_nan_and_fixed_shapes(scenario, replay_folder):
    env = make_parallel(scenario, replay_folder)
    cfg = env.config
    capacity = info_capacity(cfg.max_boxes, cfg.max_collaborators)
    _, infos = env.reset(seed=3)
    shapes: dict[str, tuple] = {}
    while env.agents:
        actions = {a: np.zeros(env.action_space(a).shape) for a in env.agents}
        _, _, _, _, infos = env.step(actions)
        for agent, info in infos.items():
            for path, leaf in walk(info):
                if isinstance(leaf, float | np.ndarray) and np.asarray(leaf).dtype.kind == "f":
                    assert not np.isnan(leaf).any(), f"{scenario} {agent}{path} holds NaN"
                if isinstance(leaf, np.ndarray):
                    assert shapes.setdefault(path, leaf.shape) == leaf.shape, path
            if info["evaluated"]:
                assert info["fused_boxes"].shape == (capacity, 7)
                assert info["fused_mask"].sum() == info["n_pred"]
                assert info["gt_mask"].sum() == min(info["n_gt"], capacity)
                for key in ("ap30", "ap50", "ap70"):
                    assert info[key] == UNDEFINED or 0.0 <= info[key] <= 1.0
            empty = ~np.isin(np.arange(cfg.max_collaborators),
                             np.arange(len(info["evaluated_collaborators"])))
            assert (info["rpe_after"][empty] == UNDEFINED).all()
            assert (info["rpe_after"][~empty] >= 0).all()


@pytest.mark.parametrize("mode", ["sync", "async"])
def test_make_vec_stacks_infos(mode):
    envs = gymnasium.make_vec("roco/CollabPerceptionEgo-v0", num_envs=2, vectorization_mode=mode,
                              scenario="urban_roundabout", max_cycles=CYCLES)
    try:
        _, infos = envs.reset(seed=[0, 1])
        for _ in range(CYCLES + 1):  # past the end: autoreset too
            _, rewards, _, _, infos = envs.step(np.zeros(envs.action_space.shape,
                                                         dtype=np.float32))
            assert rewards.shape == (2,)
        assert "rpe_after" in infos or "collaborators" in infos
    finally:
        envs.close()


@settings(max_examples=60, deadline=None)
@given(rows=st.integers(0, 6), cols=st.integers(0, 6), extra=st.integers(0, 5),
       axis=st.integers(0, 1), boolean=st.booleans())
def test_info_padding_equals_numpy_pad(rows, cols, extra, axis, boolean):
    """The info arrays' zero padding (a preallocated fill) is np.pad's, dtype included."""
    values = np.arange(rows * cols).reshape(rows, cols)
    values = (values % 2 == 0) if boolean else values.astype(np.float32)
    capacity = values.shape[axis] + extra
    widths = [(0, 0), (0, 0)]
    widths[axis] = (0, extra)
    padded = _padded(values, capacity, axis)
    assert padded.dtype == values.dtype and np.array_equal(padded, np.pad(values, widths))
