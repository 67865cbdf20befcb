"""Bring-your-own scene: FramesSource from user arrays, and its validation."""

import numpy as np
import pytest

import roco_env
from roco_env.scenario import scenario_from_dict
from roco_env.traffic import Frame, make_traffic_source

CONFIG = scenario_from_dict({"traffic": {"source": "frames"}, "agents": {"cavs": 1, "rsus": 1}})


def frames(n=3):
    out = []
    for t in range(n):
        boxes = np.array([[t * 1.0, 0.0, 0.8, 4.5, 1.9, 1.6, 0.0],
                          [20.0, 3.5, 0.8, 4.5, 1.9, 1.6, np.pi]])
        out.append(Frame(object_ids=[7, 9], object_boxes=boxes, cav_object_ids=[7],
                         rsu_poses=[[10.0, 8.0, -1.0]], object_classes=[0, 1]))
    return out


def test_frames_replay_in_order_and_hold_the_last():
    source = make_traffic_source(CONFIG, frames=frames())
    state = source.reset(np.random.default_rng(0))
    assert state.agent_ids == ("cav_0", "rsu_0")
    np.testing.assert_array_equal(state.agent_object_ids, [7, -1])
    np.testing.assert_allclose(state.agent_poses, [[0.0, 0.0, 0.0], [10.0, 8.0, -1.0]])
    np.testing.assert_array_equal(state.object_classes, [0, 1])
    assert source.step(0.1).agent_poses[0, 0] == 1.0
    assert source.step(0.1).time == pytest.approx(0.2)
    assert source.finished
    assert source.step(0.1).agent_poses[0, 0] == 2.0  # holds the last frame
    assert source.reset(None).agent_poses[0, 0] == 0.0


def test_frames_required_only_for_frames_source():
    with pytest.raises(ValueError, match="frames="):
        make_traffic_source(CONFIG)
    with pytest.raises(ValueError, match=r"needs your frames: pass frames=\[Frame\(\.\.\.\), "
                                         r"\.\.\.\] to roco_env\.parallel_env"):
        roco_env.parallel_env(CONFIG)
    synthetic = scenario_from_dict({})
    with pytest.raises(ValueError, match="frames="):
        make_traffic_source(synthetic, frames=frames())


@pytest.mark.parametrize("change, fragment", [
    ({"object_boxes": [[0, 0, 0, 1, 1]]}, "frames[1].object_boxes"),
    ({"object_ids": [7, 7]}, "frames[1].object_ids"),
    ({"cav_object_ids": [8]}, "frames[1].cav_object_ids [8]"),
    ({"object_classes": [0, 9]}, "frames[1].object_classes"),
    ({"object_velocities": [[0.0, 0.0]]}, "frames[1].object_velocities"),
    ({"rsu_poses": []}, "agent set must stay constant"),
])
def test_bad_frames_are_rejected_with_the_field(change, fragment):
    data = frames()
    bad = data[1]
    for key, value in change.items():
        setattr(bad, key, value)
    with pytest.raises(ValueError) as info:
        make_traffic_source(CONFIG, frames=data)
    assert fragment in str(info.value)


def test_env_runs_a_users_scene_with_ideal_detections():
    import roco_env

    env = roco_env.parallel_env("urban_intersection", max_cycles=3, frames=frames(),
                                detector="ideal", sigma_t=0.0, sigma_r=0.0,
                                **{"traffic.source": "frames", "agents.cavs": 1,
                                   "agents.rsus": 1})
    obs, infos = env.reset(seed=0)
    assert env.agents == ["cav_0", "rsu_0"]
    # The RSU at (10, 8) sees both cars; the CAV is car 7, so it sees car 9 only.
    assert int(obs["rsu_0"]["box_mask"].sum()) == 2
    assert int(obs["cav_0"]["box_mask"].sum()) == 1
    assert infos["cav_0"]["collaborators"][0] == "rsu_0"
    _, rewards, *_ = env.step({a: np.zeros(env.action_space(a).shape, np.float32)
                               for a in env.agents})
    assert rewards["cav_0"] == 1.0  # ideal detector, clean poses: every box found exactly


def test_frames_with_other_agent_counts_than_the_scenario_say_what_to_set():
    env = roco_env.parallel_env("urban_intersection", frames=frames(),
                                **{"traffic.source": "frames"})  # 4 CAVs + 1 RSU in its YAML
    with pytest.raises(ValueError, match=r"imply \['cav_0', 'cav_1', 'cav_2', 'cav_3', 'rsu_0'\]; "
                                         r"give the overrides cavs=1, rsus=1 to match"):
        env.reset(seed=0)


def test_users_frames_end_the_episode_at_the_last_frame():
    import roco_env

    env = roco_env.parallel_env("urban_intersection", max_cycles=10, frames=frames(3),
                                detector="ideal", sigma_t=0.0, sigma_r=0.0,
                                **{"traffic.source": "frames", "agents.cavs": 1,
                                   "agents.rsus": 1})
    env.reset(seed=0)
    truncations, scored = {}, []
    while env.agents:
        _, _, _, truncations, infos = env.step(
            {a: np.zeros(env.action_space(a).shape, np.float32) for a in env.agents})
        scored.append(infos["cav_0"]["gt_boxes"][infos["cav_0"]["gt_mask"]][:, 0].tolist())
    assert all(truncations.values())
    # car 9 at x = 20 seen from the CAV (car 7 at x = t): each frame scored exactly once
    np.testing.assert_allclose(scored, [[20.0], [19.0], [18.0]])
