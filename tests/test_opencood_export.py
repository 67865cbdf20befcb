"""The OPV2V export as OpenCOOD reads it, and the ``opencood`` ground-truth convention.

``opencood_scenarios`` re-implements OpenCOOD's folder walk and ego rule
(``opencood/data_utils/datasets/basedataset.py``, ``BaseDataset.__init__``): scenario
folders = the sorted sub-folders of the split folder (``root_dir``); per scenario the
agent folders sorted as strings, the first moved to the end when ``int()`` of it is
negative (only that one), the first of the list is the ego. ``opencood_truth``
re-implements its ground truth: the union of every agent's ``vehicles`` (ids
de-duplicated) projected into the ego's LiDAR frame, kept when all 8 corners lie in
its range box.
"""

import math
import os
from pathlib import Path

import numpy as np
import pytest
import yaml

import roco_env
from roco_env.evaluation import ground_truths
from roco_env.scenario import AgentsConfig, scenario_from_dict
from roco_env.traffic import export_opv2v, make_traffic_source
from roco_env.traffic.frames import Frame, frame_to_state
from roco_env.traffic.opv2v_export import scenario_folder

OPENCOOD_RANGE = np.array([-140.8, -40.0, -3.0, 140.8, 40.0, 1.0])  # x, y, z low; x, y, z high


def opencood_scenarios(root_dir: Path) -> list[tuple[Path, list[str]]]:
    """(scenario folder, agent folder names with the ego first), as OpenCOOD lists them."""
    scenario_folders = sorted(os.path.join(root_dir, x) for x in os.listdir(root_dir)
                              if os.path.isdir(os.path.join(root_dir, x)))
    out = []
    for scenario in scenario_folders:
        cav_list = sorted(x for x in os.listdir(scenario)
                          if os.path.isdir(os.path.join(scenario, x)))
        assert len(cav_list) > 0
        if int(cav_list[0]) < 0:  # "roadside unit data's id is always negative"
            cav_list = cav_list[1:] + [cav_list[0]]
        out.append((Path(scenario), cav_list))
    return out


def opencood_ego(cav_list: list[str]) -> str:
    return cav_list[0]


def _world_matrix(pose) -> np.ndarray:
    """OpenCOOD's x_to_world for a pose with roll = pitch = 0 (what the export writes)."""
    x, y, z, roll, yaw, pitch = pose
    assert roll == 0.0 and pitch == 0.0
    c, s = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
    return np.array([[c, -s, 0, x], [s, c, 0, y], [0, 0, 1, z], [0, 0, 0, 1]], dtype=float)


def opencood_truth(scenario: Path, cav_list: list[str], frame: str) -> set[int]:
    """Object ids of OpenCOOD's ground truth for the ego of ``cav_list`` at ``frame``."""
    files = {cav: yaml.safe_load((scenario / cav / f"{frame}.yaml").read_text())
             for cav in cav_list}
    to_lidar = np.linalg.inv(_world_matrix(files[opencood_ego(cav_list)]["lidar_pose"]))
    objects = {}
    for data in files.values():
        objects.update(data["vehicles"] or {})
    kept = set()
    for oid, obj in objects.items():
        centre = np.add(obj["location"], obj["center"])
        to_world = _world_matrix([*centre, *obj["angle"]])
        signs = np.array([[sx, sy, sz] for sx in (1, -1) for sy in (1, -1) for sz in (1, -1)])
        corners = np.c_[signs * obj["extent"], np.ones(8)] @ (to_lidar @ to_world).T
        if np.all((corners[:, :3] >= OPENCOOD_RANGE[:3]) & (corners[:, :3] <= OPENCOOD_RANGE[3:])):
            kept.add(int(oid))
    return kept


def test_the_reimplemented_rule_makes_an_rsu_the_ego_of_plain_folder_names():
    """Why the export names cav_0's folder +<id>: with plain names two RSUs make an RSU
    OpenCOOD's ego, and ids of different digit counts another CAV."""
    assert opencood_ego(sorted(["641", "650", "-1"])[1:] + ["-1"]) == "641"
    plain = sorted(["641", "7", "1000", "-1", "-2"])
    assert opencood_ego(plain[1:] + plain[:1]) == "-2"
    assert opencood_ego(sorted(["641", "7", "1000"])) == "1000"


# Scene: CAVs 641 (cav_0), 7, 1000 (ids of 3 different digit counts, cav_0 not the
# smallest); object 5 a tall truck (its top is 2.1 m above the LiDAR: out of OpenCOOD's
# z range), 12 beyond y = 40 m, 30 a car in range.
OBJECTS = {641: [0.0, 0.0, 0.8, 4.5, 1.9, 1.6, 0.3], 7: [20.0, 5.0, 0.8, 4.4, 1.8, 1.6, 0.0],
           1000: [-15.0, -6.0, 0.75, 4.6, 1.9, 1.5, 3.0],
           5: [35.0, 10.0, 2.0, 8.0, 2.5, 4.0, 1.0], 12: [10.0, 45.0, 0.8, 4.5, 1.9, 1.6, 0.0],
           30: [60.0, -20.0, 0.8, 4.5, 1.9, 1.6, -1.0]}
CAVS = [641, 7, 1000]
RSU_POSES = [[5.0, 12.0, -1.57], [-20.0, 8.0, 0.5], [30.0, -10.0, 2.0]]


def scene_states(rsus: int, frames: int = 2) -> list:
    agents = AgentsConfig(cavs=len(CAVS), rsus=rsus)
    states = []
    for k in range(frames):
        boxes = np.array(list(OBJECTS.values()))
        boxes[:, 0] += k  # everything moves 1 m along x per frame
        states.append(frame_to_state(Frame(object_ids=list(OBJECTS), object_boxes=boxes,
                                           cav_object_ids=CAVS, rsu_poses=RSU_POSES[:rsus]),
                                     agents, k))
    return states


@pytest.mark.parametrize("rsus", [0, 1, 2, 3])
def test_opencood_reads_the_export_with_cav_0_as_its_ego(tmp_path, rsus):
    states = scene_states(rsus)
    export_opv2v(states, tmp_path, split="test", scenario="2024_01_01_00_00_00")
    ((scenario, cav_list),) = opencood_scenarios(tmp_path / "test")
    assert scenario == scenario_folder(tmp_path, "test", "2024_01_01_00_00_00")
    ego = opencood_ego(cav_list)
    assert ego == "+641" and int(ego) == states[0].agent_object_ids[0]
    assert sorted(cav_list) == sorted(["+641", "7", "1000"] + [str(-k) for k in range(1, rsus + 1)])
    for k, state in enumerate(states):
        lidar = yaml.safe_load((scenario / ego / f"{k:06d}.yaml").read_text())["lidar_pose"]
        x, y, yaw = state.agent_poses[0]
        np.testing.assert_allclose([lidar[0], -lidar[1], -math.radians(lidar[4])], [x, y, yaw],
                                   atol=1e-9)
        assert lidar[2] == pytest.approx(state.sensor_heights[0])


@pytest.mark.parametrize("rsus", [0, 2])
def test_the_replay_reads_the_export_in_the_same_agent_order(tmp_path, rsus):
    states = scene_states(rsus)
    export_opv2v(states, tmp_path)
    replay = make_traffic_source(scenario_from_dict({
        "traffic": {"source": "opv2v", "path": str(scenario_folder(tmp_path))},
        "agents": {"cavs": 3, "rsus": rsus}}))
    assert replay.dataset_agent_ids == CAVS + [-k for k in range(1, rsus + 1)]
    back = replay.reset(None)
    np.testing.assert_array_equal(back.agent_object_ids, states[0].agent_object_ids)
    np.testing.assert_allclose(back.agent_poses, states[0].agent_poses, atol=1e-9)


@pytest.mark.parametrize("rsus", [0, 2])
def test_opencood_ground_truth_convention_matches_opencood_on_the_export(tmp_path, rsus):
    states = scene_states(rsus)
    export_opv2v(states, tmp_path)
    ((scenario, cav_list),) = opencood_scenarios(tmp_path / "test")
    for k, state in enumerate(states):
        (_, ids), = ground_truths(state, np.zeros((state.num_agents, state.num_objects), bool),
                                  [(0, ())], [-140.8, 140.8], [-40.0, 40.0], "opencood",
                                  [-3.0, 1.0])
        expected = opencood_truth(scenario, cav_list, f"{k:06d}")
        assert set(ids.tolist()) == expected == {641, 7, 1000, 30}  # own car in, 5 and 12 out


def test_visible_convention_is_the_default_and_leaves_the_own_car_out():
    state = scene_states(1, frames=1)[0]
    visible = np.ones((state.num_agents, state.num_objects), bool)
    ranges = ([-140.8, 140.8], [-40.0, 40.0])
    (boxes, ids), = ground_truths(state, visible, [(0, (1,))], *ranges)
    (boxes_v, ids_v), = ground_truths(state, visible, [(0, (1,))], *ranges, "visible")
    np.testing.assert_array_equal(boxes, boxes_v)
    assert set(ids.tolist()) == {7, 1000, 5, 30}  # the tall truck counts, the own car not
    with pytest.raises(ValueError, match=r"evaluation.ground_truth must be one of "
                                         r"\['visible', 'opencood'\]; got 'all'"):
        ground_truths(state, visible, [(0, ())], *ranges, "all")


def test_env_scores_against_the_opencood_ground_truth_when_asked():
    def first_step(**overrides):
        env = roco_env.parallel_env("urban_intersection", cavs=2, rsus=0, sigma_t=0.0,
                                    sigma_r=0.0, **overrides)
        env.reset(seed=0)
        _, _, _, _, infos = env.step({a: np.zeros(env.action_space(a).shape)
                                      for a in env.agents})
        return infos["cav_0"]

    def nearest_truth(info):  # m from the ego's sensor to the nearest ground-truth box
        gt = info["gt_boxes"][info["gt_mask"]]
        return np.hypot(gt[:, 0], gt[:, 1]).min()

    default = first_step()
    np.testing.assert_array_equal(
        default["gt_boxes"], first_step(**{"evaluation.ground_truth": "visible"})["gt_boxes"])
    opencood = first_step(**{"evaluation.ground_truth": "opencood"})
    assert nearest_truth(default) > 2.0  # the own car is not ground truth by default
    assert nearest_truth(opencood) < 0.5  # it is in OpenCOOD's (centred under the sensor)


@pytest.mark.parametrize("value", ["everything", 3])
def test_a_bad_ground_truth_convention_names_the_field(value):
    from roco_env.scenario import ConfigError

    with pytest.raises(ConfigError, match="evaluation.ground_truth"):
        scenario_from_dict({"evaluation": {"ground_truth": value}})
    with pytest.raises(ConfigError, match="evaluation.z_range"):
        scenario_from_dict({"evaluation": {"z_range": [1.0, -3.0]}})
