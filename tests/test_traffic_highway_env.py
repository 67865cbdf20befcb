"""highway-env adapter: frame conversion, stable ids, CAVs, class-attribute isolation."""

import numpy as np
import pytest

from roco_env.geometry import wrap_angle
from roco_env.scenario import scenario_from_dict
from roco_env.traffic import make_traffic_source
from roco_env.traffic.highway_env_source import HighwayEnvSource, he_to_world

pytest.importorskip("highway_env")
from highway_env.vehicle.behavior import IDMVehicle  # noqa: E402


def make(layout, cavs=2, rsus=1, density=1.0):
    config = scenario_from_dict({"traffic": {"source": "highway_env", "layout": layout,
                                             "density": density, "lanes": 3},
                                 "agents": {"cavs": cavs, "rsus": rsus}})
    return make_traffic_source(config)


def test_he_to_world_mirrors_y_and_negates_heading():
    pose = he_to_world(np.array([10.0, 0.0]), np.array([4.0, -2.0]), np.array([0.0, 0.3]))
    np.testing.assert_allclose(pose, [[10.0, -4.0, 0.0], [0.0, 2.0, -0.3]])
    # heading pi stays pi (wrapped into (-pi, pi])
    assert he_to_world(np.zeros(1), np.zeros(1), np.array([np.pi]))[0, 2] == pytest.approx(np.pi)


def test_highway_vehicle_along_x_stays_along_x_with_y_mirrored():
    src = make("highway")
    assert isinstance(src, HighwayEnvSource)
    src.reset(np.random.default_rng(0))
    for _ in range(3):
        state = src.step(0.1)
    vehicles = src.env.unwrapped.road.vehicles
    by_id = {src._stable_id(v): v for v in vehicles}
    for row, oid in enumerate(state.object_ids):
        v = by_id[int(oid)]
        np.testing.assert_allclose(state.object_boxes[row, :2], [v.position[0], -v.position[1]])
        assert state.object_boxes[row, 6] == pytest.approx(wrap_angle(-v.heading), abs=1e-12)
        np.testing.assert_allclose(state.object_velocities[row],
                                   [v.velocity[0], -v.velocity[1]])
    # everyone drives along +x on highway-v0: yaw near 0 and positive x speed
    assert np.all(np.abs(state.object_boxes[:, 6]) < 0.3)
    assert np.all(state.object_velocities[:, 0] > 0.0)
    # highway-env lanes are at y >= 0 (right of the first lane) -> y <= 0 in the world
    assert np.all(state.object_boxes[:, 1] < 1.0)


def test_controlled_vehicles_are_cavs_and_ids_are_stable():
    src = make("highway", cavs=2)
    first = src.reset(np.random.default_rng(1))
    controlled = src.env.unwrapped.controlled_vehicles
    assert first.agent_ids == ("cav_0", "cav_1", "rsu_0")
    for k, vehicle in enumerate(controlled):
        np.testing.assert_allclose(first.agent_poses[k, :2],
                                   [vehicle.position[0], -vehicle.position[1]])
    ids_before = {id(v): src._stable_id(v) for v in src.env.unwrapped.road.vehicles}
    state = src.step(0.1)
    for v in src.env.unwrapped.road.vehicles:
        assert src._stable_id(v) == ids_before[id(v)]
    np.testing.assert_array_equal(state.agent_object_ids, first.agent_object_ids)


def test_determinism_from_seed():
    states = []
    for _ in range(2):
        src = make("merge", cavs=2)
        src.reset(np.random.default_rng(3))
        states.append(src.step(0.1))
    np.testing.assert_array_equal(states[0].object_boxes, states[1].object_boxes)
    np.testing.assert_array_equal(states[0].agent_poses, states[1].agent_poses)


def test_intersection_class_attributes_do_not_leak():
    before = dict(vars(IDMVehicle))
    src = make("intersection", cavs=2)
    src.reset(np.random.default_rng(0))
    src.step(0.1)
    assert {k: v for k, v in vars(IDMVehicle).items() if k.isupper()} == \
        {k: v for k, v in before.items() if k.isupper()}
    # the scene keeps its own (low jam distance) parameters for its own steps
    assert src._scene_attrs[IDMVehicle]["DISTANCE_WANTED"] == 7
    assert IDMVehicle.DISTANCE_WANTED == before["DISTANCE_WANTED"] != 7


def test_intersection_objects_change_but_agents_do_not():
    src = make("intersection", cavs=2, density=3.0)
    first = src.reset(np.random.default_rng(2))
    seen = {tuple(first.object_ids)}
    for _ in range(15):
        state = src.step(0.1)
        seen.add(tuple(state.object_ids))
        assert state.agent_ids == first.agent_ids
    assert len(seen) > 1  # vehicles were spawned or removed
    # a CAV whose vehicle leaves the road stays an object, frozen at its last box
    cav_vehicle = src.env.unwrapped.controlled_vehicles[1]
    last = state.object_boxes[np.searchsorted(state.object_ids, state.agent_object_ids[1])]
    src.env.unwrapped.road.vehicles.remove(cav_vehicle)
    after = src._world()
    row = np.searchsorted(after.object_ids, after.agent_object_ids[1])
    np.testing.assert_allclose(after.object_boxes[row], last)
    np.testing.assert_allclose(after.object_velocities[row], 0.0)


def test_merge_extra_cavs_are_near_the_ego_and_bad_inputs():
    src = make("merge", cavs=3, rsus=0)
    state = src.reset(np.random.default_rng(0))
    assert state.agent_ids == ("cav_0", "cav_1", "cav_2")
    assert len(set(state.agent_object_ids.tolist())) == 3
    with pytest.raises(ValueError, match="dt"):
        src.step(0.5)
    with pytest.raises(ValueError, match="traffic.layout"):
        make("parking_lot")
