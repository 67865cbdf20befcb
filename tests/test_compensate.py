"""Delay-aware alignment: box tracks over a sender's messages (roco_env.comm.tracking), the
``compensate`` policy wrapper, the env's own compensation (``comm.compensation: track``),
and motion read as pose error without them."""

from __future__ import annotations

import numpy as np
import pytest

import roco_env
from roco_env.comm.tracking import BoxTracker, TrackingParams, moved_boxes, world_centres
from roco_env.policies import make_policy
from roco_env.policies.compensate import Compensate
from roco_env.sweeps.cells import build_grid
from roco_env.sweeps.episode import run_episode
from roco_env.traffic.frames import Frame

LATE = {"delay": "fixed", "delay_ms": 200}


def test_tracks_learn_each_objects_velocity_and_drop_the_lost():
    rng = np.random.default_rng(0)
    tracker = BoxTracker(TrackingParams(measurement_std=0.1))
    start = np.array([[0.0, 0.0], [40.0, 3.5], [20.0, -10.0]])
    velocity = np.array([[25.0, 0.0], [-30.0, 0.0], [0.0, 0.0]])
    for step in range(12):
        time = 0.1 * step + 0.03 * (step % 3)  # irregular instants
        seen = start + velocity * time + rng.normal(0.0, 0.1, start.shape)
        rows = tracker.update(time, seen if step < 8 else seen[:2])  # the third leaves
    estimate, known = tracker.velocities(rows)
    assert known.all() and len(tracker.tracks) == 2  # dropped after max_missed messages
    np.testing.assert_allclose(estimate, velocity[:2], atol=0.8)
    assert list(BoxTracker().update(0.0, start)) == [0, 1, 2]


def test_a_single_measurement_knows_no_velocity():
    tracker = BoxTracker()
    rows = tracker.update(0.0, np.array([[1.0, 2.0]]))
    velocity, known = tracker.velocities(rows)
    assert not known.any() and not velocity.any()


def test_moved_boxes_move_along_the_world_velocity_in_the_senders_frame():
    pose = np.array([10.0, -5.0, np.pi / 2])
    boxes = np.array([[3.0, 1.0, 0.8, 4.5, 1.9, 1.6, 0.2]])
    moved = moved_boxes(boxes, pose, np.array([[2.0, 0.0]]), 0.5)
    np.testing.assert_allclose(world_centres(moved, pose) - world_centres(boxes, pose), [[1.0, 0.0]],
                               atol=1e-12)
    np.testing.assert_array_equal(moved[:, 2:], boxes[:, 2:])


class _Spy:
    """A base policy that keeps the observations it is called with."""

    def __init__(self):
        self.seen = []

    def __call__(self, observation, info=None):
        self.seen.append(observation)
        return np.zeros((len(observation["collab_mask"]), 3), dtype=np.float32)


def _road(steps: int) -> list[Frame]:
    """A straight road: two CAVs at 10 m/s, traffic at 12 m/s both ways, a row of parked
    cars along the kerb; one frame per 0.1 s."""
    parked = [(100 + k, -20.0 + 8.0 * k, 7.0, 0.0) for k in range(8)]
    movers = [(200 + k, -30.0 + 10.0 * k, -3.5, 12.0) for k in range(7)]
    movers += [(300 + k, -30.0 + 10.0 * k, 3.5, -12.0) for k in range(7)]
    cars = [(0, 0.0, 0.0, 10.0), (1, 18.0, 0.0, 10.0), *parked, *movers]
    frames = []
    for step in range(steps):
        t = 0.1 * step
        frames.append(Frame(
            object_ids=[c[0] for c in cars],
            object_boxes=[[x + v * t, y, 0.8, 4.5, 1.9, 1.6, 0.0 if v >= 0 else np.pi]
                          for _, x, y, v in cars],
            cav_object_ids=[0, 1], object_velocities=[[v, 0.0] for *_, v in cars]))
    return frames


def _late_episode(wrapper: Compensate, steps: int) -> list[tuple]:
    """Every agent's (observation, the one its base saw, info, object id -> speed m/s now)
    per step of :func:`_road`."""
    env = roco_env.parallel_env("highway_dense", max_cycles=steps, cavs=2, rsus=0,
                                sigma_t=0.0, sigma_r=0.0, frames=_road(steps + 1),
                                **{**LATE, "traffic.source": "frames"})
    spy = wrapper.policy = _Spy()
    observations, infos = env.reset(seed=0)
    out = []
    while env.agents:
        state = env._frame.state
        speed = dict(zip(state.object_ids.tolist(), np.hypot(*state.object_velocities.T),
                         strict=True))
        actions = {}
        for agent in env.agents:
            actions[agent] = wrapper(observations[agent], infos[agent])
            out.append((observations[agent], spy.seen[-1], infos[agent], speed))
        observations, _, _, _, infos = env.step(actions)
    return out


def _box_errors(observation: dict, info: dict, env) -> np.ndarray:
    """Distances (m) between each collaborator box of ``observation`` moved with the true
    relative pose and its object now, in the ego's frame."""
    truth = info["privileged"]
    frame = env._frame.state
    ego = env.possible_agents.index(info["agent"])
    rows = {int(o): k for k, o in enumerate(frame.object_ids)}
    errors = []
    for slot in np.flatnonzero(observation["collab_mask"]):
        pose = truth["true_relative_poses"][slot]
        c, s = np.cos(pose[2]), np.sin(pose[2])
        for box, object_id in zip(observation["collab_boxes"][slot],
                                  truth["collab_box_object_ids"][slot], strict=True):
            if object_id < 0:
                continue
            here = pose[:2] + np.array([c * box[0] - s * box[1], s * box[0] + c * box[1]])
            world = frame.object_boxes[rows[int(object_id)], :2]
            ego_pose = frame.agent_poses[ego]
            ce, se = np.cos(ego_pose[2]), np.sin(ego_pose[2])
            local = np.array([[ce, se], [-se, ce]]) @ (world - ego_pose[:2])
            errors.append(np.hypot(*(here - local)))
    return np.array(errors)


def test_extrapolated_boxes_stand_where_their_objects_are_now():
    """The observations are read at the step they were returned (the env's current frame)."""
    env = roco_env.parallel_env("highway_dense", max_cycles=8, cavs=3, sigma_t=0.0,
                                sigma_r=0.0, **LATE)
    wrapper = make_policy("compensate", base="identity")
    spy = wrapper.policy = _Spy()
    observations, infos = env.reset(seed=0)
    before, after = [], []
    for _ in range(8):
        for agent in env.agents:
            wrapper(observations[agent], infos[agent])
            if observations[agent]["collab_mask"].any():
                before.append(_box_errors(observations[agent], infos[agent], env))
                after.append(_box_errors(spy.seen[-1], infos[agent], env))
        observations, _, _, _, infos = env.step({a: np.zeros((5, 3)) for a in env.agents})
    late, fixed = np.concatenate(before[-6:]), np.concatenate(after[-6:])
    assert np.median(late) > 0.5  # 200 ms of dense highway traffic
    assert np.median(fixed) < 0.5 * np.median(late)


def test_the_env_compensation_moves_the_fused_boxes_too():
    env = roco_env.parallel_env("highway_dense", max_cycles=8, cavs=3, sigma_t=0.0,
                                sigma_r=0.0, **LATE, **{"comm.compensation": "track"})
    observations, infos = env.reset(seed=0)
    errors = []
    for _ in range(8):
        observations, _, _, _, infos = env.step({a: np.zeros((5, 3)) for a in env.agents})
        assert all(info["compensated"] for info in infos.values())
        errors += [_box_errors(observations[a], infos[a], env) for a in env.agents
                   if observations[a]["collab_mask"].any()]
    assert np.median(np.concatenate(errors[-6:])) < 1.0


def test_static_mode_keeps_only_boxes_that_stand_still():
    """Parked cars beside moving traffic: the boxes kept, the ego's own and its
    collaborators', are parked cars'."""
    wrapper = make_policy("compensate", base="identity", mode="static")
    kept, dropped = [], []
    for given, seen, info, speed in _late_episode(wrapper, 10)[-8:]:
        truth = info["privileged"]
        pairs = [(given["box_mask"], seen["box_mask"], truth["box_object_ids"])]
        pairs += [(given["collab_box_mask"][slot], seen["collab_box_mask"][slot],
                   truth["collab_box_object_ids"][slot])
                  for slot in np.flatnonzero(seen["collab_mask"])]
        for before, after, ids in pairs:
            for was, keep, object_id in zip(before, after, ids, strict=True):
                if was and object_id >= 0:
                    (kept if keep else dropped).append(speed[int(object_id)])
    kept, dropped = np.array(kept), np.array(dropped)
    assert kept.size > 10 and not kept.any()  # no moving box kept
    # a young track's velocity is too uncertain to call a box parked: some wait
    assert kept.size > 0.25 * (kept.size + np.sum(dropped == 0.0))


def test_without_the_network_the_base_sees_the_observation_as_it_is():
    wrapper = make_policy("compensate", base="identity")
    spy = wrapper.policy = _Spy()
    env = roco_env.parallel_env("highway_dense", max_cycles=2, cavs=3)
    observations, infos = env.reset(seed=0)
    wrapper(observations["cav_0"], infos["cav_0"])
    assert spy.seen[-1] is observations["cav_0"]
    late = roco_env.parallel_env("highway_dense", max_cycles=2, cavs=3, **LATE)
    observations, infos = late.reset(seed=0)
    with pytest.raises(ValueError, match="'time'"):
        wrapper(observations["cav_0"], {})


def test_bad_compensate_parameters_name_the_field():
    with pytest.raises(ValueError, match="mode='fast'.*extrapolate"):
        make_policy("compensate", mode="fast")
    with pytest.raises(ValueError, match="static_speed"):
        make_policy("compensate", static_speed=-1.0)
    with pytest.raises(ValueError, match="tau2"):
        make_policy("compensate", base="roco", tau2=-1.0)  # the base's own parameter


def test_motion_is_read_as_pose_error_unless_compensated():
    """Pose noise 0, 200 ms: every box matcher "corrects" moving boxes; compensated, the
    reported (true) pose stands."""
    results = {}
    for policy in ("roco", "compensate:base=roco"):
        (cell,) = build_grid(["highway_dense"], [0.0], [policy], [0], 10, overrides=LATE)
        results[policy], _ = run_episode(cell)
    assert results["roco"]["rpe_t_median"] > 0.3 and results["roco"]["worse_share"] > 0.3
    compensated = results["compensate:base=roco"]
    assert compensated["rpe_t_median"] <= 0.2 and compensated["worse_share"] < 0.15
