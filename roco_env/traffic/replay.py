"""Dataset replay: OPV2V / V2XSet label folders and DAIR-V2X cooperative labels.

Only labels and poses are read (no point clouds). Everything is loaded and
validated when the source is built, so a bad file raises :class:`ReplayError`
(a ValueError naming the path and the problem) and nothing half-loaded is
ever returned. Conversions happen here and nowhere else (frames: docs/conventions.md).

OPV2V / V2XSet (``traffic.source: opv2v``, ``traffic.path`` = one scenario folder)
  ``<scenario>/<agent id>/<frame>.yaml``; CARLA frame: left-handed, degrees.
  ``lidar_pose`` = [x, y, z, roll, yaw, pitch];
  ``vehicles: {id: {location, center, angle [roll, yaw, pitch], extent (half
  sizes), speed (km/h)}}``; box centre = location + center. Converted with
  y -> -y, yaw -> -yaw (radians). Agent folders with id >= 0 are CAVs (sorted by
  id; a folder named ``+<id>`` comes first: cav_0, the OpenCOOD ego of an
  export, see :mod:`roco_env.traffic.opv2v_export`), negative ids are RSUs (V2XSet;
  ordered -1, -2, ...). Every agent folder is replayed: ``agents.cavs`` and
  ``agents.rsus`` must equal the folder counts, and every folder must hold the
  same frames (both checked at load, errors naming the fields / the folder and
  frame). A CAV's pose is its ``lidar_pose``. Objects = union of all agents'
  lists; nothing else: a CAV's own car is an object only when another agent
  lists it (an OPV2V agent never lists itself). A CAV no list holds has no box:
  it is in no ground truth, occludes nothing and no one detects it (its
  ``agent_object_ids`` entry is its folder id, matching no object). An optional
  ``obj_type`` (car/van/truck/bus) restores the class.

DAIR-V2X cooperative (``traffic.source: dair``, ``traffic.path`` = dataset root)
  ``cooperative/data_info.json`` lists frame pairs; vehicle pose =
  ``novatel_to_world`` * ``lidar_to_novatel`` (vehicle-side calib), RSU pose =
  ``virtuallidar_to_world`` with ``system_error_offset`` (delta_x, delta_y) added
  to its translation (the corrected pose; ``""`` means no offset, as in the
  official devkit); objects from
  ``cooperative/label_world/*.json`` ``world_8_points`` (right-handed, metres);
  label types other than car/van/truck/bus (pedestrians, cyclists) are skipped.
  A box follows DAIR's corner order (corners 0-3 one face, 4-7 the other, heading
  = corner 3 -> 0, length |0-3|, width |0-1|, as the dataset tools write them);
  its height is the label's ``3d_dimensions.h`` when given, else the length of
  the edges 0-4 .. 3-7 (not the z extent of a tilted box). Corners in any other
  order fall back to an order-free fit whose heading is only known modulo pi.
  DAIR cooperative frames are independent samples: object ids are per frame
  (1, 2, ... in label order). The vehicle's own car is an object only as far as
  the labels hold it: no box is made up for it; its ``agent_object_ids`` entry is
  0, which no object has.
  One CAV (``cav_0``) and at most one RSU (``rsu_0``); the RSU's calibration and
  ``system_error_offset`` are read only when ``agents.rsus`` is 1.

Ground: every agent's ground height (``WorldState.ground_heights``) is its LiDAR
z minus the scenario's sensor height (``agents.cav_height`` / ``rsu_height``), so
sensing measures heights above the ground under the agent whatever the
recording's world z.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from roco_env.geometry import wrap_angle
from roco_env.scenario import AgentsConfig, ScenarioConfig
from roco_env.traffic.frames import SequenceSource
from roco_env.traffic.state import OBJECT_CLASSES, WorldState


class ReplayError(ValueError):
    """A dataset folder or file is missing or malformed; the message names the path."""


_BaseLoader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


class FloatSafeLoader(_BaseLoader):  # type: ignore[misc, valid-type]
    """yaml SafeLoader that also reads exponent floats without a dot (``1e-5``)."""


FloatSafeLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


def load_yaml(path: Path) -> Any:
    """Parse a YAML file safely (exponent floats supported); ReplayError naming the path."""
    if not path.is_file():
        raise ReplayError(f"{path}: file not found")
    try:
        return yaml.load(path.read_text(), Loader=FloatSafeLoader)  # noqa: S506 (safe loader)
    except yaml.YAMLError as exc:
        raise ReplayError(f"{path}: malformed YAML: {exc}") from exc


def load_json(path: Path) -> Any:
    """Parse a JSON file; ReplayError naming the path."""
    if not path.is_file():
        raise ReplayError(f"{path}: file not found")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ReplayError(f"{path}: malformed JSON: {exc}") from exc


def _numbers(path: Path, value: Any, key: str, size: int) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise ReplayError(f"{path}: {key} must be {size} numbers, got {value!r}") from exc
    if arr.size != size or not np.all(np.isfinite(arr)):
        raise ReplayError(f"{path}: {key} must be {size} finite numbers, got {value!r}")
    return arr


def _get(path: Path, mapping: Any, key: str) -> Any:
    if not isinstance(mapping, dict) or key not in mapping:
        raise ReplayError(f"{path}: missing key {key!r}")
    return mapping[key]


def class_index(name: Any) -> int | None:
    """Index into OBJECT_CLASSES of a label's type name (case-insensitive); None if it is
    not a vehicle class (pedestrians, cyclists are skipped)."""
    name = str(name).lower()
    return OBJECT_CLASSES.index(name) if name in OBJECT_CLASSES else None


def carla_pose_to_world(pose6: np.ndarray) -> np.ndarray:
    """CARLA [x, y, z, roll, yaw, pitch] (m, deg, left-handed) -> world (x, y, yaw rad)."""
    return np.array([pose6[0], -pose6[1], wrap_angle(-np.deg2rad(pose6[4]))])


def _opv2v_object(path: Path, key: str, entry: Any) -> tuple[int, np.ndarray, float, int]:
    where = f"vehicles.{key}"
    location = _numbers(path, _get(path, entry, "location"), f"{where}.location", 3)
    center = _numbers(path, _get(path, entry, "center"), f"{where}.center", 3)
    angle = _numbers(path, _get(path, entry, "angle"), f"{where}.angle", 3)
    extent = _numbers(path, _get(path, entry, "extent"), f"{where}.extent", 3)
    speed = float(_numbers(path, _get(path, entry, "speed"), f"{where}.speed", 1)[0]) / 3.6
    xyz = location + center
    yaw = wrap_angle(-np.deg2rad(angle[1]))
    box = np.array([xyz[0], -xyz[1], xyz[2], *(2.0 * extent), yaw])
    cls = class_index(entry.get("obj_type", "car")) or 0
    try:
        oid = int(key)
    except (TypeError, ValueError) as exc:
        raise ReplayError(f"{path}: vehicle id {key!r} is not an integer") from exc
    return oid, box, speed, cls


def _numbered_folders(folder: Path) -> list[Path]:
    """The sub-folders of ``folder`` named by an agent id (``641``, ``-1``, ``+641``)."""
    return [p for p in folder.iterdir() if p.is_dir() and re.fullmatch(r"[-+]?\d+", p.name)]


def _agent_folders(root: Path) -> dict[int, Path]:
    """Agent id -> folder of a scenario, in agent order: CAVs (a ``+``-named folder, the
    OpenCOOD ego of an export, first; then by id), then RSUs (-1, -2, ...)."""
    if not root.is_dir():
        raise ReplayError(f"{root}: dataset folder not found (set traffic.path to an OPV2V/"
                          "V2XSet scenario folder holding <agent id>/<frame>.yaml)")
    folders = _numbered_folders(root)
    if not folders:
        inside = sorted(p for p in [*root.glob("*"), *root.glob("*/*")]
                        if p.is_dir() and _numbered_folders(p))
        hint = (f"; scenario folders below it: {', '.join(map(str, inside[:3]))} (an OPV2V root "
                "or an export's <folder>/<split>/<scenario>): set traffic.path to one of "
                "them") if inside else ""
        raise ReplayError(f"{root}: no agent folders (<agent id>/ with <frame>.yaml files)"
                          + hint)
    by_id: dict[int, Path] = {}
    for folder in folders:
        if int(folder.name) in by_id:
            raise ReplayError(f"{root}: agent folders {by_id[int(folder.name)].name!r} and "
                              f"{folder.name!r} name the same id")
        by_id[int(folder.name)] = folder

    def order(agent: int) -> tuple:
        return (agent < 0, not by_id[agent].name.startswith("+"), abs(agent))

    return {agent: by_id[agent] for agent in sorted(by_id, key=order)}


def _check_agent_counts(root: Path, agents_found: list[int], agents: AgentsConfig) -> None:
    """Refuse a config whose agent counts differ from the folder's (no agent silently dropped)."""
    cavs = [a for a in agents_found if a >= 0]
    rsus = [a for a in agents_found if a < 0]
    if len(cavs) != agents.cavs or len(rsus) != agents.rsus:
        raise ReplayError(
            f"{root}: holds {len(cavs)} CAV folders {cavs} and {len(rsus)} RSU folders {rsus}; "
            f"agents.cavs={agents.cavs} and agents.rsus={agents.rsus} must equal them: set "
            f"agents.cavs={len(cavs)} agents.rsus={len(rsus)} (overrides cavs={len(cavs)} "
            f"rsus={len(rsus)}); to replay fewer agents, point traffic.path at a copy of the "
            "scenario holding only their folders")


def _common_frames(root: Path, folders: dict[int, Path]) -> list[str]:
    """The frame names (sorted) every agent folder holds; ReplayError naming the folder and
    the frames it lacks when the folders disagree."""
    held = {folder: {p.stem for p in folder.glob("*.yaml")} for folder in folders.values()}
    frames = set().union(*held.values())
    if not frames:
        raise ReplayError(f"{root}: no <frame>.yaml files in the agent folders")
    for folder, have in held.items():
        missing = sorted(frames - have)
        if missing:
            raise ReplayError(
                f"{folder}: frame(s) {', '.join(missing[:5])} missing "
                f"({len(missing)} of the {len(frames)} frames the other agent folders hold); "
                "every agent folder must hold the same <frame>.yaml files")
    return sorted(frames)


def load_opv2v(root: str | Path, config: ScenarioConfig) -> tuple[list[WorldState], list[int]]:
    """All frames of an OPV2V/V2XSet scenario folder as WorldStates, plus the dataset ids
    of the agents (CAVs then RSUs)."""
    root = Path(root)
    folders = _agent_folders(root)
    agents = list(folders)
    _check_agent_counts(root, agents, config.agents)
    states = [_opv2v_state(folders, frame, index * config.traffic.dt, config.agents)
              for index, frame in enumerate(_common_frames(root, folders))]
    return states, agents


def _opv2v_state(folders: dict[int, Path], frame: str, time: float,
                 config: AgentsConfig) -> WorldState:
    """One frame: every agent's pose and the union of the objects they list."""
    objects: dict[int, tuple[np.ndarray, float, int]] = {}
    poses, lidar_z = [], []
    for folder in folders.values():
        path = folder / f"{frame}.yaml"
        data = load_yaml(path)
        lidar = _numbers(path, _get(path, data, "lidar_pose"), "lidar_pose", 6)
        poses.append(carla_pose_to_world(lidar))
        lidar_z.append(lidar[2])
        vehicles = _get(path, data, "vehicles") or {}
        if not isinstance(vehicles, dict):
            raise ReplayError(f"{path}: vehicles must be a mapping id -> object")
        for key, entry in vehicles.items():
            oid, box, speed, cls = _opv2v_object(path, key, entry)
            objects.setdefault(oid, (box, speed, cls))
    ids = np.array(sorted(objects), dtype=np.int64)
    boxes = np.array([objects[i][0] for i in ids]).reshape(-1, 7)
    speed = np.array([objects[i][1] for i in ids])
    vel = speed[:, None] * np.column_stack([np.cos(boxes[:, 6]), np.sin(boxes[:, 6])])
    classes = np.array([objects[i][2] for i in ids], dtype=np.int64)
    cavs = [agent for agent in folders if agent >= 0]
    return _replay_state(time, ids, classes, boxes, vel, cavs, np.array(poses), lidar_z, config)


def _replay_state(time: float, ids: np.ndarray, classes: np.ndarray, boxes: np.ndarray,
                  velocities: np.ndarray, cav_object_ids: Any, poses: np.ndarray,
                  lidar_z: Any, agents: AgentsConfig) -> WorldState:
    """A replayed frame: objects (world boxes, m / rad), then CAVs and RSUs at their LiDAR
    poses (``poses`` (A, 3) world x, y, yaw; CAVs first), the ground under each = its
    LiDAR z minus its sensor height. ``cav_object_ids``: each CAV's own vehicle id, which
    need not be among ``ids`` (no label describes it); RSUs get -1.

    Built here rather than with :func:`roco_env.traffic.agents.make_world`, which takes a
    CAV's pose from its box: a replayed CAV may have none."""
    n_cav = len(cav_object_ids)
    n_rsu = poses.shape[0] - n_cav
    heights = np.r_[np.full(n_cav, agents.cav_height), np.full(n_rsu, agents.rsu_height)]
    return WorldState(
        time=float(time), object_ids=ids, object_classes=classes, object_boxes=boxes,
        object_velocities=velocities,
        agent_ids=tuple(f"cav_{i}" for i in range(n_cav)) + tuple(f"rsu_{i}" for i in range(n_rsu)),
        agent_kinds=("cav",) * n_cav + ("rsu",) * n_rsu,
        agent_poses=poses.reshape(-1, 3),
        agent_object_ids=np.r_[np.asarray(cav_object_ids, dtype=np.int64),
                               -np.ones(n_rsu, np.int64)],
        sensor_heights=heights,
        sensor_ranges=np.r_[np.full(n_cav, agents.cav_range), np.full(n_rsu, agents.rsu_range)],
        comm_ranges=np.full(n_cav + n_rsu, agents.comm_range),
        ground_heights=np.asarray(lidar_z, dtype=float) - heights,
    )


def _transform(path: Path, data: Any, key: str | None = None) -> np.ndarray:
    """4x4 matrix from a DAIR calib dict {rotation 3x3, translation 3x1} (optionally nested)."""
    node = _get(path, data, key) if key else data
    rot = _numbers(path, _get(path, node, "rotation"), "rotation", 9).reshape(3, 3)
    trans = _numbers(path, _get(path, node, "translation"), "translation", 3)
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rot, trans
    return out


def _matrix_to_pose(mat: np.ndarray) -> np.ndarray:
    return np.array([mat[0, 3], mat[1, 3], np.arctan2(mat[1, 0], mat[0, 0])])


def _in_dair_order(pts: np.ndarray, tol: float = 0.05) -> bool:
    """Whether 8 corners are in DAIR's order: 0-3 a rectangle (0-1 and 3-2 the width
    edges, 3->0 and 2->1 the length edges), 4-7 the same face shifted along the box's
    vertical edges. ``tol``: metres, and the cosine allowed between length and width."""
    low, up = pts[:4], pts[4:]
    length, width = low[0] - low[3], low[0] - low[1]
    rectangle = (np.linalg.norm(low[1] - low[2] - length) < tol
                 and np.linalg.norm(low[3] - low[2] - width) < tol)
    norms = np.linalg.norm(length) * np.linalg.norm(width)
    square = norms > 0 and abs(length @ width) < tol * norms
    shift = up - low
    prism = bool(np.all(np.linalg.norm(shift - shift.mean(axis=0), axis=1) < tol))
    return bool(rectangle and square and prism)


def box_from_8_points(path: Path, points: Any, height: float | None = None) -> np.ndarray:
    """Box (x, y, z, l, w, h, yaw) of a cuboid given by its 8 corners (m).

    Corners in DAIR's order (see the module docstring) give the heading 3 -> 0,
    length |0-3|, width |0-1| and height = the vertical edges' length (exact for a
    tilted box too). Any other order: the longer horizontal edge is the length and
    the heading its direction, known only modulo pi (folded into +-90 deg), the
    height the z extent. ``height`` (the label's own, m) overrides either.
    """
    pts = _numbers(path, points, "world_8_points", 24).reshape(8, 3)
    centre = pts.mean(axis=0)
    if _in_dair_order(pts):
        forward = pts[[0, 1, 4, 5]].mean(axis=0) - pts[[3, 2, 7, 6]].mean(axis=0)
        side = pts[[0, 3, 4, 7]].mean(axis=0) - pts[[1, 2, 5, 6]].mean(axis=0)
        edge = float(np.linalg.norm(pts[4:] - pts[:4], axis=1).mean())
        return np.array([*centre, np.linalg.norm(forward), np.linalg.norm(side),
                         edge if height is None else height, np.arctan2(forward[1], forward[0])])
    bottom = pts[np.argsort(pts[:, 2], kind="stable")[:4], :2]
    ring = bottom[np.argsort(np.arctan2(*(bottom - bottom.mean(0)).T[::-1]))]
    edges = np.roll(ring, -1, axis=0) - ring
    lengths = np.hypot(edges[:, 0], edges[:, 1])
    k = int(np.argmax(lengths))
    yaw = np.arctan2(edges[k, 1], edges[k, 0])
    if abs(wrap_angle(yaw)) > np.pi / 2:
        yaw += np.pi
    if height is None:
        height = np.ptp(pts[:, 2])
    return np.array([*centre, lengths[k], lengths[(k + 1) % 4], height, wrap_angle(yaw)])


def load_dair(root: str | Path, config: ScenarioConfig) -> list[WorldState]:
    """All frames of a DAIR-V2X cooperative dataset root as WorldStates."""
    root = Path(root)
    if not root.is_dir():
        raise ReplayError(f"{root}: DAIR-V2X dataset folder not found (set traffic.path to the "
                          "folder holding cooperative/, vehicle-side/, infrastructure-side/)")
    if config.agents.cavs != 1 or config.agents.rsus > 1:
        raise ReplayError(f"{root}: DAIR-V2X has one vehicle and one RSU; agents.cavs must be 1 "
                          f"and agents.rsus 0 or 1 (got {config.agents.cavs}, {config.agents.rsus})")
    info_path = root / "cooperative" / "data_info.json"
    info = load_json(info_path)
    if not isinstance(info, list) or not info:
        raise ReplayError(f"{info_path}: must be a non-empty list of frame pairs")
    states = []
    for index, item in enumerate(info):
        veh_frame = Path(_get(info_path, item, "vehicle_pointcloud_path")).stem
        calib = root / "vehicle-side" / "calib"
        p1, p2 = calib / "lidar_to_novatel" / f"{veh_frame}.json", \
            calib / "novatel_to_world" / f"{veh_frame}.json"
        veh = _transform(p2, load_json(p2)) @ _transform(p1, load_json(p1), "transform")
        inf = _dair_rsu(root, info_path, item) if config.agents.rsus else None
        label_path = root / _get(info_path, item, "cooperative_label_path")
        labels = load_json(label_path)
        if not isinstance(labels, list):
            raise ReplayError(f"{label_path}: must be a list of labelled objects")
        vehicles = [obj for obj in labels
                    if class_index(_get(label_path, obj, "type")) is not None]
        boxes = [box_from_8_points(label_path, _get(label_path, obj, "world_8_points"),
                                   _label_height(label_path, obj))
                 for obj in vehicles]
        classes = [class_index(obj["type"]) for obj in vehicles]
        ids = np.arange(1, len(boxes) + 1, dtype=np.int64)  # 0 is the vehicle's own id
        rsu = np.zeros((0, 3)) if inf is None else _matrix_to_pose(inf)[None]
        lidar_z = [veh[2, 3]] + ([] if inf is None else [inf[2, 3]])
        states.append(_replay_state(
            index * config.traffic.dt, ids, np.array(classes, dtype=np.int64),
            np.array(boxes).reshape(-1, 7), np.zeros((ids.size, 2)), [0],
            np.vstack([_matrix_to_pose(veh)[None], rsu]), lidar_z, config.agents))
    return states


def _dair_rsu(root: Path, info_path: Path, item: Any) -> np.ndarray:
    """4x4 RSU LiDAR-to-world of a frame pair, corrected by its ``system_error_offset``."""
    inf_frame = Path(_get(info_path, item, "infrastructure_pointcloud_path")).stem
    offset = _get(info_path, item, "system_error_offset")
    if offset == "":  # the official devkit's "no offset"
        offset = {"delta_x": 0.0, "delta_y": 0.0}
    delta = _numbers(info_path, [_get(info_path, offset, "delta_x"),
                                 _get(info_path, offset, "delta_y")],
                     "system_error_offset (delta_x, delta_y)", 2)
    path = root / "infrastructure-side" / "calib" / "virtuallidar_to_world" / f"{inf_frame}.json"
    inf = _transform(path, load_json(path))
    inf[:2, 3] += delta
    return inf


def _label_height(path: Path, obj: Any) -> float | None:
    """The label's ``3d_dimensions.h`` (m) when it has one."""
    dims = obj.get("3d_dimensions") if isinstance(obj, dict) else None
    if dims is None or "h" not in dims:
        return None
    height = float(_numbers(path, dims["h"], "3d_dimensions.h", 1)[0])
    if height <= 0:
        raise ReplayError(f"{path}: 3d_dimensions.h must be > 0, got {height}")
    return height


def _require_path(config: ScenarioConfig) -> str:
    if not config.traffic.path:
        raise ReplayError(
            f"traffic.source={config.traffic.source!r} needs a dataset folder: set the override "
            "traffic.path=<folder> (e.g. load_scenario('opv2v_replay', "
            "**{'traffic.path': '/data/opv2v/test/2021_08_18_19_48_05'}))"
        )
    return config.traffic.path


class OPV2VReplay(SequenceSource):
    """Replay of an OPV2V/V2XSet scenario folder (``traffic.path``); one frame per step.
    ``dataset_agent_ids`` maps agent order (cav_0.., rsu_0..) to the dataset's ids."""

    def __init__(self, config: ScenarioConfig) -> None:
        states, self.dataset_agent_ids = load_opv2v(_require_path(config), config)
        super().__init__(states)


class DairReplay(SequenceSource):
    """Replay of a DAIR-V2X cooperative dataset root (``traffic.path``); one frame per step."""

    def __init__(self, config: ScenarioConfig) -> None:
        super().__init__(load_dair(_require_path(config), config))
