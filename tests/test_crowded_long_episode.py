"""What a long crowded_intersection episode does (documented in its scenario file): the
traffic is steady (lanes are cyclic, nobody leaves), but the CAVs drive out towards the ends
of the 300 m roads, so each ego's ground truth thins out after ~100 steps."""

import numpy as np

from roco_env.scenario import load_scenario
from roco_env.traffic.synthetic import make_synthetic


def test_traffic_stays_while_the_cavs_drive_out():
    source = make_synthetic(load_scenario("crowded_intersection"))
    world = source.reset(np.random.default_rng(0))
    count, cavs = world.object_boxes.shape[0], world.agent_object_ids[:4]

    def near_centre(world) -> int:
        return int((np.abs(world.object_boxes[:, :2]) < 50.0).all(axis=1).sum())

    def cav_distance(world) -> float:
        return float(np.hypot(*world.agent_poses[:4, :2].T).mean())

    start_near, start_distance = near_centre(world), cav_distance(world)
    for _ in range(500):
        world = source.step(0.1)
    assert world.object_boxes.shape[0] == count
    assert np.array_equal(world.agent_object_ids[:4], cavs)
    assert near_centre(world) >= 0.75 * start_near  # the crossing stays crowded
    assert start_distance < 30.0 < 120.0 < cav_distance(world) < 150.0  # roads end at 150 m
