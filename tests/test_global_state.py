"""env.state() / env.state_space: the fixed-size global state for centralised critics."""

import numpy as np
import pytest

import roco_env
from roco_env.global_state import pack_state, unpack_state
from roco_env.scenario import list_scenarios

REPLAY = {"opv2v_replay"}  # needs a dataset folder


@pytest.mark.parametrize("name", sorted(set(list_scenarios()) - REPLAY))
def test_state_is_in_its_space_and_holds_the_truth(name):
    env = roco_env.parallel_env(name, max_cycles=2, max_objects=32)
    env.reset(seed=1)
    for _ in range(2):
        state = env.state()
        assert env.state_space.contains(state)
        world = env._frame.state
        parts = unpack_state(state, len(env.possible_agents), 32)
        np.testing.assert_allclose(parts["true_poses"], world.agent_poses, atol=1e-4)
        np.testing.assert_allclose(parts["reported_poses"], env._frame.reported_poses,
                                   atol=1e-4)
        filled = parts["box_mask"].sum()
        assert filled == min(world.num_objects, 32)
        assert not parts["boxes"][filled:].any()
        env.step({a: np.zeros(env.action_space(a).shape) for a in env.agents})


def test_overfull_scene_keeps_the_boxes_nearest_the_agents():
    env = roco_env.parallel_env("crowded_intersection", max_objects=4)
    env.reset(seed=0)
    world = env._frame.state
    assert world.num_objects > 4
    kept = unpack_state(pack_state(world, env._frame.reported_poses, 4), world.num_agents, 4)
    gaps = np.hypot(*(world.object_boxes[:, None, :2] - world.agent_poses[None, :, :2])
                    .transpose(2, 0, 1)).min(axis=1)
    nearest = world.object_boxes[np.argsort(gaps, kind="stable")[:4]]
    np.testing.assert_allclose(kept["boxes"], nearest, atol=1e-3)


def test_state_before_reset_and_wrong_shapes():
    env = roco_env.parallel_env(cavs=2, rsus=0)
    with pytest.raises(ValueError, match="before reset"):
        env.state()
    with pytest.raises(ValueError, match="must have shape"):
        unpack_state(np.zeros(5), 2, 4)
