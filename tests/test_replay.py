"""Dataset replay (OPV2V/V2XSet, DAIR-V2X) on hand-written fixtures, export round trip."""

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from roco_env.geometry import wrap_angle
from roco_env.scenario import scenario_from_dict
from roco_env.traffic import export_opv2v, make_traffic_source
from roco_env.traffic.replay import FloatSafeLoader, ReplayError, box_from_8_points

# --- OPV2V / V2XSet fixture: CAVs 641 and 650, RSU -1 (V2XSet), two frames -------------

CAV_641 = """ego_speed: 18.0
lidar_pose: [10.0, 20.0, 1.9, 0.0, 90.0, 0.0]
true_ego_pos: [10.0, 20.0, 0.0, 0.0, 90.0, 0.0]
vehicles:
  650:
    angle: [0.0, -30.0, 0.0]
    center: [0.1, 0.2, 0.8]
    extent: [2.3, 0.95, 0.8]
    location: [{x650}, 5.0, 0.0]
    speed: 36.0
  700:
    angle: [1e-5, 180.0, 0.0]
    center: [0.0, 0.0, 1.5]
    extent: [5.0, 1.25, 1.5]
    location: [1e-5, -3e+1, 0.0]
    speed: 0.0
"""
# CAV 641 as the other agents list it (an OPV2V agent never lists itself).
VEHICLE_641 = """vehicles:
  641:
    angle: [0.0, 90.0, 0.0]
    center: [0.0, 0.0, 0.75]
    extent: [2.25, 0.9, 0.75]
    location: [10.0, 20.0, 0.0]
    speed: 18.0
"""
CAV_650 = """ego_speed: 36.0
lidar_pose: [{x650}, 5.0, 1.9, 0.0, -30.0, 0.0]
true_ego_pos: [{x650}, 5.0, 0.0, 0.0, -30.0, 0.0]
""" + VEHICLE_641
RSU = """lidar_pose: [0.0, 0.0, 5.5, 0.0, 45.0, 0.0]
true_ego_pos: [0.0, 0.0, 5.5, 0.0, 45.0, 0.0]
""" + VEHICLE_641


def write_opv2v(root: Path) -> Path:
    scenario = root / "2021_08_18_19_48_05"
    for frame, x650 in (("000068", 30.0), ("000070", 31.0)):
        for agent, text in (("641", CAV_641), ("650", CAV_650), ("-1", RSU)):
            path = scenario / agent / f"{frame}.yaml"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text.format(x650=x650))
    return scenario


def exported_scenario(root: Path) -> Path:
    """The scenario folder of an export (``<root>/<split>/<scenario>``)."""
    (scenario,) = root.glob("*/*")
    return scenario


def opv2v_config(path, cavs=2, rsus=1):
    return scenario_from_dict({"traffic": {"source": "opv2v", "path": str(path)},
                               "agents": {"cavs": cavs, "rsus": rsus}})


def test_opv2v_fixture_loads_to_expected_boxes(tmp_path):
    source = make_traffic_source(opv2v_config(write_opv2v(tmp_path)))
    state = source.reset(np.random.default_rng(0))
    assert state.agent_ids == ("cav_0", "cav_1", "rsu_0")
    np.testing.assert_array_equal(state.object_ids, [641, 650, 700])
    np.testing.assert_array_equal(state.agent_object_ids, [641, 650, -1])
    expected = np.array([
        [10.0, -20.0, 0.75, 4.5, 1.8, 1.5, -math.pi / 2],
        [30.1, -5.2, 0.8, 4.6, 1.9, 1.6, math.radians(30.0)],
        [1e-5, 30.0, 1.5, 10.0, 2.5, 3.0, math.pi],
    ])
    got = state.object_boxes.copy()
    np.testing.assert_allclose(got[:, :6], expected[:, :6], atol=1e-9)
    np.testing.assert_allclose(wrap_angle(got[:, 6] - expected[:, 6]), 0.0, atol=1e-9)
    np.testing.assert_allclose(state.object_velocities[1],
                               10.0 * np.array([math.cos(math.radians(30)),
                                                math.sin(math.radians(30))]))
    np.testing.assert_allclose(state.agent_poses, [[10.0, -20.0, -math.pi / 2],
                                                   [30.0, -5.0, math.radians(30.0)],
                                                   [0.0, 0.0, -math.pi / 4]], atol=1e-12)
    np.testing.assert_allclose(state.sensor_heights, [1.9, 1.9, 5.5])
    nxt = source.step(0.1)
    assert nxt.object_boxes[1, 0] == pytest.approx(31.1)
    assert source.finished and source.step(0.1).object_boxes[1, 0] == pytest.approx(31.1)


def test_rsu_handling(tmp_path):
    scenario = write_opv2v(tmp_path)
    state = make_traffic_source(opv2v_config(scenario)).reset(None)
    assert -1 not in state.object_ids  # an RSU is never an object
    assert make_traffic_source(opv2v_config(scenario)).dataset_agent_ids == [641, 650, -1]


@pytest.mark.parametrize("cavs, rsus", [(2, 0), (1, 1), (2, 2), (3, 1)])
def test_agent_counts_must_match_the_folders(tmp_path, cavs, rsus):
    with pytest.raises(ReplayError) as info:
        make_traffic_source(opv2v_config(write_opv2v(tmp_path), cavs=cavs, rsus=rsus))
    assert (f"holds 2 CAV folders [641, 650] and 1 RSU folders [-1]; agents.cavs={cavs} and "
            f"agents.rsus={rsus} must equal them: set agents.cavs=2 agents.rsus=1") \
        in str(info.value)


def test_a_4_cav_1_rsu_export_is_not_replayed_with_2_cavs(tmp_path):
    import roco_env

    config = scenario_from_dict({"traffic": {"layout": "intersection", "length": 100.0,
                                             "density": 4.0}, "agents": {"cavs": 4, "rsus": 1}})
    source = make_traffic_source(config)
    export_opv2v([source.reset(np.random.default_rng(3))], tmp_path / "export")
    path = str(exported_scenario(tmp_path / "export"))
    with pytest.raises(ReplayError, match=r"agents.cavs=2 and agents.rsus=0 must equal them: "
                                          r"set agents.cavs=4 agents.rsus=1"):
        roco_env.parallel_env("opv2v_replay", **{"traffic.path": path})
    env = roco_env.parallel_env("opv2v_replay", cavs=4, rsus=1, **{"traffic.path": path})
    assert len(env.possible_agents) == 5


def test_float_aware_loader_is_still_safe():
    assert yaml.load("a: 1e-5\nb: -3e+1\nc: 7\nd: 1.5", Loader=FloatSafeLoader) == \
        {"a": 1e-5, "b": -30.0, "c": 7, "d": 1.5}
    with pytest.raises(yaml.YAMLError):
        yaml.load("!!python/object/apply:os.system ['true']", Loader=FloatSafeLoader)


@pytest.mark.parametrize("damage, fragment", [
    (lambda s: (s / "650" / "000070.yaml").unlink(), "650: frame(s) 000070 missing"),
    (lambda s: (s / "641" / "000070.yaml").write_text("vehicles: [1, 2\n"), "malformed YAML"),
    (lambda s: (s / "641" / "000070.yaml").write_text(
        CAV_641.format(x650=1.0).replace("    extent: [2.3, 0.95, 0.8]\n", "")),
     "missing key 'extent'"),
    (lambda s: (s / "641" / "000068.yaml").write_text(
        CAV_641.format(x650=1.0).replace("lidar_pose", "lidar_posse")), "'lidar_pose'"),
    (lambda s: (s / "641" / "000068.yaml").write_text(
        CAV_641.format(x650="abc")), "vehicles.650.location"),
])
def test_bad_opv2v_input_names_the_path(tmp_path, damage, fragment):
    scenario = write_opv2v(tmp_path)
    damage(scenario)
    with pytest.raises(ReplayError) as info:
        make_traffic_source(opv2v_config(scenario))
    assert fragment in str(info.value)
    assert str(scenario) in str(info.value)


@pytest.mark.parametrize("agent", ["641", "650", "-1"])
def test_a_frame_missing_in_one_agent_folder_is_refused_at_load(tmp_path, agent):
    scenario = write_opv2v(tmp_path)
    (scenario / agent / "000068.yaml").unlink()
    with pytest.raises(ReplayError) as info:
        make_traffic_source(opv2v_config(scenario))
    assert f"{scenario / agent}: frame(s) 000068 missing (1 of the 2 frames" in str(info.value)


def test_missing_folder_and_missing_path(tmp_path):
    with pytest.raises(ReplayError, match="dataset folder not found"):
        make_traffic_source(opv2v_config(tmp_path / "nope"))
    with pytest.raises(ReplayError, match="traffic.path"):
        make_traffic_source(scenario_from_dict({"traffic": {"source": "opv2v"}}))
    (tmp_path / "empty").mkdir()
    with pytest.raises(ReplayError, match="no agent folders"):
        make_traffic_source(opv2v_config(tmp_path / "empty"))


def test_an_export_root_as_traffic_path_names_its_scenario_folder(tmp_path):
    """Exports used to put the agent folders straight into the folder; now they are two
    levels down (<folder>/<split>/<scenario>/): the error says where."""
    write_opv2v(tmp_path / "export" / "test")  # -> export/test/<scenario>/<agent>/
    (scenario,) = (tmp_path / "export" / "test").iterdir()
    for root in (tmp_path / "export", tmp_path / "export" / "test"):
        with pytest.raises(ReplayError, match=rf"no agent folders .*; scenario folders below "
                           rf"it: {re.escape(str(scenario))} \(an OPV2V root or an export's"):
            make_traffic_source(opv2v_config(root))


@pytest.mark.parametrize("layout", ["intersection", "parking_lot"])
def test_round_trip_synthetic_export_replay(tmp_path, layout):
    config = scenario_from_dict({"traffic": {"layout": layout, "length": 100.0,
                                             "density": 0.8 if layout == "parking_lot" else 4.0},
                                 "agents": {"cavs": 3, "rsus": 1}})
    source = make_traffic_source(config)
    states = [source.reset(np.random.default_rng(11))]
    states += [source.step(0.1) for _ in range(4)]
    export_opv2v(states, tmp_path / "episode")
    replay = make_traffic_source(opv2v_config(exported_scenario(tmp_path / "episode"),
                                              cavs=3, rsus=1))
    replayed = [replay.reset(None)] + [replay.step(0.1) for _ in range(4)]
    for a, b in zip(states, replayed, strict=True):
        assert a.agent_ids == b.agent_ids and a.agent_kinds == b.agent_kinds
        np.testing.assert_array_equal(a.object_ids, b.object_ids)
        np.testing.assert_array_equal(a.object_classes, b.object_classes)
        np.testing.assert_array_equal(a.agent_object_ids, b.agent_object_ids)
        np.testing.assert_allclose(a.object_boxes[:, :6], b.object_boxes[:, :6], atol=1e-6)
        np.testing.assert_allclose(wrap_angle(a.object_boxes[:, 6] - b.object_boxes[:, 6]), 0,
                                   atol=1e-6)
        np.testing.assert_allclose(a.object_velocities, b.object_velocities, atol=1e-6)
        np.testing.assert_allclose(a.agent_poses, b.agent_poses, atol=1e-6)
        assert a.time == pytest.approx(b.time, abs=1e-6)


# --- DAIR-V2X cooperative fixture -----------------------------------------------------

def corners(box, pitch=0.0):
    """The 8 corners in DAIR's order (0-3 bottom: front-right, front-left, rear-left,
    rear-right; 4-7 the top), optionally pitched (rad) about the box's own y axis."""
    x, y, z, length, w, h, yaw = box
    c, s = math.cos(yaw), math.sin(yaw)
    cp, sp = math.cos(pitch), math.sin(pitch)
    pts = []
    half = length / 2
    for dz in (-h / 2, h / 2):
        for dx, dy in ((half, -w / 2), (half, w / 2), (-half, w / 2), (-half, -w / 2)):
            fx, fz = cp * dx + sp * dz, -sp * dx + cp * dz
            pts.append([x + c * fx - s * dy, y + s * fx + c * dy, z + fz])
    return pts


def rot_z(yaw):
    c, s = math.cos(yaw), math.sin(yaw)
    return [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]


DAIR_BOXES = [[100.0, 50.0, 0.8, 4.4, 1.8, 1.6, 0.3], [120.0, 40.0, 1.6, 11.0, 2.5, 3.2, -1.2]]


def write_dair(root: Path, dz: float = 0.0) -> Path:
    """The DAIR fixture; ``dz`` raises the whole recording (world z) by that many metres."""
    def dump(rel, data):
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(data))

    info = []
    for k, (veh, inf) in enumerate((("015344", "000009"), ("015345", "000010"))):
        info.append({
            "vehicle_pointcloud_path": f"vehicle-side/velodyne/{veh}.pcd",
            "infrastructure_pointcloud_path": f"infrastructure-side/velodyne/{inf}.pcd",
            "cooperative_label_path": f"cooperative/label_world/{veh}.json",
            "system_error_offset": {"delta_x": 0.5, "delta_y": -0.25},
        })
        dump(f"vehicle-side/calib/lidar_to_novatel/{veh}.json",
             {"transform": {"rotation": rot_z(0.1), "translation": [[1.0], [0.0], [1.9]]}})
        dump(f"vehicle-side/calib/novatel_to_world/{veh}.json",
             {"rotation": rot_z(0.5), "translation": [[90.0 + k], [45.0], [dz]]})
        dump(f"infrastructure-side/calib/virtuallidar_to_world/{inf}.json",
             {"rotation": rot_z(-2.0), "translation": [[110.0], [60.0], [5.5 + dz]]})
        labels = [{"type": "Car" if i == 0 else "Bus",
                   "world_8_points": corners([*b[:2], b[2] + dz, *b[3:]])}
                  for i, b in enumerate(DAIR_BOXES)]
        labels.append({"type": "Pedestrian", "world_8_points": corners(
            [105.0, 55.0, 0.9 + dz, 0.6, 0.6, 1.8, 0.0])})
        dump(f"cooperative/label_world/{veh}.json", labels)
    dump("cooperative/data_info.json", info)
    return root


def dair_config(path, rsus=1):
    return scenario_from_dict({"traffic": {"source": "dair", "path": str(path)},
                               "agents": {"cavs": 1, "rsus": rsus}})


def test_dair_fixture_loads_poses_and_boxes(tmp_path):
    source = make_traffic_source(dair_config(write_dair(tmp_path)))
    state = source.reset(None)
    assert state.agent_ids == ("cav_0", "rsu_0")
    # vehicle LiDAR pose = novatel_to_world * lidar_to_novatel
    x = 90.0 + math.cos(0.5) * 1.0
    y = 45.0 + math.sin(0.5) * 1.0
    np.testing.assert_allclose(state.agent_poses[0], [x, y, 0.6], atol=1e-12)
    # RSU pose includes the system error offset
    np.testing.assert_allclose(state.agent_poses[1], [110.5, 59.75, -2.0], atol=1e-12)
    assert state.num_objects == 2  # car + bus; the pedestrian is skipped, no ego box made up
    np.testing.assert_array_equal(state.object_classes, [0, 3])
    np.testing.assert_allclose(state.object_boxes[:, :6], np.array(DAIR_BOXES)[:, :6],
                               atol=1e-9)
    np.testing.assert_allclose(state.object_boxes[:, 6], np.array(DAIR_BOXES)[:, 6],
                               atol=1e-9)  # DAIR's corner order gives the full heading
    np.testing.assert_array_equal(state.object_ids, [1, 2])
    np.testing.assert_array_equal(state.agent_object_ids, [0, -1])  # no box is the vehicle's
    assert source.step(0.1).agent_poses[0, 0] == pytest.approx(x + 1.0)


def test_box_from_8_points_any_corner_order():
    box = [3.0, -2.0, 1.0, 6.0, 2.0, 2.0, 2.5]
    pts = np.array(corners(box))[[5, 2, 7, 0, 3, 6, 1, 4]]
    out = box_from_8_points(Path("x.json"), pts.tolist())
    np.testing.assert_allclose(out[:6], box[:6], atol=1e-9)
    assert abs(math.sin(out[6] - box[6])) < 1e-9


@pytest.mark.parametrize("damage, fragment", [
    (lambda r: (r / "vehicle-side/calib/novatel_to_world/015345.json").unlink(),
     "novatel_to_world/015345.json: file not found"),
    (lambda r: (r / "cooperative/data_info.json").write_text("[{"), "malformed JSON"),
    (lambda r: (r / "cooperative/label_world/015344.json").write_text(
        json.dumps([{"type": "Car"}])), "missing key 'world_8_points'"),
    (lambda r: (r / "cooperative/label_world/015344.json").write_text(
        json.dumps([{"type": "Car", "world_8_points": [[0, 0, 0]]}])), "24 finite numbers"),
])
def test_bad_dair_input_names_the_path(tmp_path, damage, fragment):
    root = write_dair(tmp_path)
    damage(root)
    with pytest.raises(ReplayError) as info:
        make_traffic_source(dair_config(root))
    assert fragment in str(info.value)
    with pytest.raises(ReplayError, match="dataset folder not found"):
        make_traffic_source(dair_config(tmp_path / "nope"))


def test_replay_episode_truncates_at_the_last_frame(tmp_path):
    import roco_env

    env = roco_env.parallel_env("opv2v_replay", max_cycles=50, rsus=1,
                                **{"traffic.path": str(write_opv2v(tmp_path))})
    env.reset(seed=0)
    steps = 0
    while env.agents:
        _, _, _, truncations, _ = env.step(
            {a: np.zeros(env.action_space(a).shape) for a in env.agents})
        steps += 1
    assert steps == 2 and all(truncations.values())  # the fixture has two frames


def raise_opv2v(scenario: Path, dz: float) -> None:
    """Raise every height of an OPV2V/V2XSet folder (poses and vehicles) by ``dz`` m."""
    for path in scenario.glob("*/*.yaml"):
        data = yaml.safe_load(path.read_text())
        for key in ("lidar_pose", "true_ego_pos"):
            data[key][2] += dz
        for entry in (data.get("vehicles") or {}).values():
            entry["location"][2] += dz
        path.write_text(yaml.safe_dump(data))


def _visibility(config):
    from roco_env.sensing.visibility import compute_visibility

    state = make_traffic_source(config).reset(None)
    return state, compute_visibility(state)


@pytest.mark.parametrize("dz", [10.0, -3.0])
def test_opv2v_scene_raised_is_seen_as_on_the_ground(tmp_path, dz):
    flat_state, flat = _visibility(opv2v_config(write_opv2v(tmp_path / "flat")))
    raised_folder = write_opv2v(tmp_path / "raised")
    raise_opv2v(raised_folder, dz)
    state, raised = _visibility(opv2v_config(raised_folder))
    np.testing.assert_allclose(state.ground_heights, flat_state.ground_heights + dz)
    np.testing.assert_allclose(state.object_boxes[:, 2], flat_state.object_boxes[:, 2] + dz)
    assert flat.returns.sum() > 0
    np.testing.assert_allclose(raised.fraction, flat.fraction, atol=1e-12)
    np.testing.assert_allclose(raised.returns, flat.returns, rtol=1e-9)


def test_dair_scene_at_20m_is_seen_as_on_the_ground(tmp_path):
    flat_state, flat = _visibility(dair_config(write_dair(tmp_path / "flat")))
    state, raised = _visibility(dair_config(write_dair(tmp_path / "raised", dz=20.0)))
    np.testing.assert_allclose(flat_state.ground_heights, 0.0, atol=1e-9)
    np.testing.assert_allclose(state.ground_heights, 20.0, atol=1e-9)
    assert flat.returns.sum() > 0
    np.testing.assert_allclose(raised.fraction, flat.fraction, atol=1e-12)
    np.testing.assert_allclose(raised.returns, flat.returns, rtol=1e-9)


def test_dair_realistic_detector_scores_a_raised_scene_like_a_flat_one(tmp_path):
    import roco_env

    def ap(root):
        env = roco_env.parallel_env("opv2v_replay", max_cycles=2, sigma_t=0.0, sigma_r=0.0,
                                    detector="realistic", **{"traffic.source": "dair",
                                    "traffic.path": str(root), "agents.cavs": 1,
                                    "agents.rsus": 1})
        env.reset(seed=0)
        _, _, _, _, infos = env.step({a: np.zeros(env.action_space(a).shape)
                                      for a in env.agents})
        return [(i["n_gt"], i["n_pred"], i["ap50"]) for i in infos.values()]

    flat = ap(write_dair(tmp_path / "flat"))
    assert sum(n_pred for _, n_pred, _ in flat) > 0
    assert ap(write_dair(tmp_path / "raised", dz=20.0)) == flat


@pytest.mark.parametrize("yaw", [0.3, 2.5, -2.9])
def test_box_from_dair_corners_keeps_heading_and_the_tilted_height(yaw):
    box = [3.0, -2.0, 1.0, 6.0, 2.0, 2.5, yaw]
    pts = corners(box, pitch=math.radians(8.0))  # on a slope: the z extent exceeds h
    out = box_from_8_points(Path("x.json"), pts)
    np.testing.assert_allclose(out[:6], box[:6], atol=1e-9)
    assert out[6] == pytest.approx(yaw, abs=1e-9)
    assert np.ptp(np.array(pts)[:, 2]) > box[5] + 0.3
    assert box_from_8_points(Path("x.json"), pts, height=2.4)[5] == 2.4


def test_dair_label_height_wins_and_bad_values_name_the_file(tmp_path):
    root = write_dair(tmp_path)
    label = root / "cooperative/label_world/015344.json"
    objects = json.loads(label.read_text())
    objects[0]["3d_dimensions"] = {"h": 1.55, "w": 1.8, "l": 4.4}
    label.write_text(json.dumps(objects))
    state = make_traffic_source(dair_config(root)).reset(None)
    assert state.object_boxes[0, 5] == 1.55
    objects[0]["3d_dimensions"]["h"] = "tall"
    label.write_text(json.dumps(objects))
    with pytest.raises(ReplayError, match="015344.json: 3d_dimensions.h"):
        make_traffic_source(dair_config(root))


def test_dair_bad_system_error_offset_names_the_file(tmp_path):
    root = write_dair(tmp_path)
    info_path = root / "cooperative/data_info.json"
    info = json.loads(info_path.read_text())
    info[1]["system_error_offset"]["delta_x"] = "abc"
    info_path.write_text(json.dumps(info))
    with pytest.raises(ReplayError, match=r"data_info.json: system_error_offset"):
        make_traffic_source(dair_config(root))
    assert make_traffic_source(dair_config(root, rsus=0)).num_frames == 2  # RSU unused


def test_dair_without_rsu_needs_no_rsu_calibration(tmp_path):
    root = write_dair(tmp_path)
    for path in (root / "infrastructure-side").rglob("*.json"):
        path.unlink()
    state = make_traffic_source(dair_config(root, rsus=0)).reset(None)
    assert state.agent_ids == ("cav_0",)
    with pytest.raises(ReplayError, match="virtuallidar_to_world"):
        make_traffic_source(dair_config(root, rsus=1))


def test_a_dair_replay_exports_and_replays_back(tmp_path):
    state = make_traffic_source(dair_config(write_dair(tmp_path / "dair"))).reset(None)
    export_opv2v([state], tmp_path / "export")
    back = make_traffic_source(opv2v_config(exported_scenario(tmp_path / "export"), cavs=1,
                                            rsus=1)).reset(None)
    np.testing.assert_array_equal(back.object_ids, state.object_ids)
    np.testing.assert_array_equal(back.agent_object_ids, state.agent_object_ids)
    np.testing.assert_allclose(back.object_boxes[:, :6], state.object_boxes[:, :6], atol=1e-6)
    np.testing.assert_allclose(back.agent_poses, state.agent_poses, atol=1e-9)


def test_dair_empty_system_error_offset_means_no_offset(tmp_path):
    root = write_dair(tmp_path)
    info_path = root / "cooperative/data_info.json"
    info = json.loads(info_path.read_text())
    info[0]["system_error_offset"] = ""  # as the official devkit reads it: no offset
    info_path.write_text(json.dumps(info))
    source = make_traffic_source(dair_config(root))
    np.testing.assert_allclose(source.reset(None).agent_poses[1], [110.0, 60.0, -2.0],
                               atol=1e-12)
    np.testing.assert_allclose(source.step(0.1).agent_poses[1], [110.5, 59.75, -2.0],
                               atol=1e-12)


def test_opv2v_cav_no_one_lists_has_no_box(tmp_path):
    """Ground truth holds only what the data holds: no box is made up for CAV 650."""
    import roco_env

    scenario = write_opv2v(tmp_path)
    for frame in ("000068", "000070"):  # nobody lists CAV 650 any more
        path = scenario / "641" / f"{frame}.yaml"
        data = yaml.safe_load(path.read_text())
        del data["vehicles"][650]
        path.write_text(yaml.safe_dump(data))
    state = make_traffic_source(opv2v_config(scenario)).reset(None)
    np.testing.assert_array_equal(state.object_ids, [641, 700])
    np.testing.assert_array_equal(state.agent_object_ids, [641, 650, -1])
    np.testing.assert_allclose(state.agent_poses[1], [30.0, -5.0, math.radians(30.0)],
                               atol=1e-12)  # the CAV itself is still there, at its LiDAR pose
    env = roco_env.parallel_env("opv2v_replay", cavs=2, rsus=1, sigma_t=0.0, sigma_r=0.0,
                                **{"traffic.path": str(scenario)})
    env.reset(seed=0)
    _, _, _, _, infos = env.step({a: np.zeros(env.action_space(a).shape) for a in env.agents})
    truth = {a: i["gt_boxes"][i["gt_mask"]] for a, i in infos.items() if "gt_mask" in i}
    assert truth and all(n <= 2 for n in map(len, truth.values()))  # 641 and 700 at most


def test_export_of_a_raised_replay_round_trips_its_ground(tmp_path):
    folder = write_opv2v(tmp_path / "raised")
    raise_opv2v(folder, 10.0)
    state = make_traffic_source(opv2v_config(folder)).reset(None)
    export_opv2v([state], tmp_path / "again")
    back = make_traffic_source(opv2v_config(exported_scenario(tmp_path / "again"))).reset(None)
    np.testing.assert_allclose(back.ground_heights, state.ground_heights, atol=1e-9)
    np.testing.assert_allclose(back.object_boxes[:, :6], state.object_boxes[:, :6], atol=1e-6)
