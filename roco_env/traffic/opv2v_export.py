"""Write any episode (a list of WorldStates) as OPV2V-format label folders.

Layout: OpenCOOD's root layout ``<folder>/<split>/<scenario>/<agent>/<frame:06d>.yaml``
(``split`` default ``test``, ``scenario`` default ``scene``; OpenCOOD's ``root_dir`` /
``validate_dir`` is ``<folder>/<split>``, the replay's ``traffic.path`` is
``<folder>/<split>/<scenario>``, see :func:`scenario_folder`), with CARLA conventions
(left-handed: y -> -y, yaw -> -yaw, degrees).

Agent folder names: a CAV's object id (>= 0, as in OPV2V where it is the CARLA
actor id), RSUs ``-1, -2, ...`` (V2XSet style), and cav_0's id with a ``+``
(``+641``). OpenCOOD sorts the agent folders as strings, moves the first one
to the end if ``int()`` of it is negative (only one) and takes the first as
its ego: ``+`` sorts before ``-`` and the digits, so its ego is cav_0 whatever
the RSU count and the ids' digit counts (with plain names two RSUs make an RSU
its ego, and ``1000`` sorts before ``641``). ``int("+641")`` is 641, so the
folder still names the id.

Each file holds the agent's ``lidar_pose`` (sensor at its height above the
ground under the agent), ``true_ego_pos`` (ground level; the RSU's equals its
lidar pose), ``ego_speed`` (km/h; left out for a CAV whose own vehicle is not
among the objects), and ``vehicles``: every object but the agent itself, with
``location`` = (x, y, 0), ``center`` = (0, 0, z), ``angle`` = [0, yaw, 0],
``extent`` = half sizes, ``speed`` (km/h) and ``obj_type`` (car/van/truck/bus).
Reading it back with :func:`roco_env.traffic.replay.load_opv2v` gives the same
world (when at least two agents exist, so every CAV is listed by another agent,
and the object ids of cav_1, cav_2, ... increase, the order in which the replay
sorts the CAV folders after the ``+`` one).
"""

from __future__ import annotations

import shutil
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import yaml

from roco_env.traffic.state import OBJECT_CLASSES, WorldState

_Dumper = getattr(yaml, "CSafeDumper", yaml.SafeDumper)  # the C emitter when available


def _carla_pose(x: float, y: float, z: float, yaw: float) -> list[float]:
    return [float(x), float(-y), float(z), 0.0, float(-np.rad2deg(yaw)), 0.0]


DEFAULT_SPLIT = "test"
DEFAULT_SCENARIO = "scene"


def scenario_folder(folder: str | Path, split: str = DEFAULT_SPLIT,
                    scenario: str = DEFAULT_SCENARIO) -> Path:
    """The scenario folder an export into ``folder`` writes (the replay's ``traffic.path``)."""
    return Path(folder) / split / scenario


def _is_agent_folder(path: Path) -> bool:
    """An OPV2V agent folder: an integer name holding only ``*.yaml`` label files."""
    try:
        int(path.name)
    except ValueError:
        return False
    return path.is_dir() and all(p.is_file() and p.suffix == ".yaml" for p in path.iterdir())


def _is_export(path: Path, depth: int) -> bool:
    """Whether ``path`` is an earlier export's tree: ``depth`` folder levels (split,
    scenario) above agent folders and nothing else."""
    if depth == 0:
        return _is_agent_folder(path)
    return path.is_dir() and all(_is_export(child, depth - 1) for child in path.iterdir())


def prepare_export_folder(folder: str | Path, overwrite: bool) -> None:
    """Make ``folder`` ready for a fresh export: refuse a non-empty one unless ``overwrite``.

    Overwriting removes only earlier exports (``<split>/<scenario>/<agent id>/*.yaml``, or
    ``<agent id>/*.yaml``, the layout exports had before OpenCOOD's); anything else in the
    folder is left alone and makes the export refuse (two scenes must never mix).
    """
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"export folder {folder} is a file, not a folder")
    if not folder.exists() or not any(folder.iterdir()):
        return
    if not overwrite:
        raise ValueError(f"export folder {folder} is not empty; exporting into it would mix "
                         "two scenes: choose an empty folder or pass overwrite (--overwrite)")
    foreign = sorted(p.name for p in folder.iterdir()
                     if not (_is_export(p, depth=2) or _is_agent_folder(p)))
    if foreign:
        raise ValueError(f"export folder {folder} holds {foreign[:3]}, which are not OPV2V agent "
                         "folders of an earlier export (<split>/<scenario>/<agent id>/*.yaml, "
                         "or <agent id>/*.yaml); overwrite only replaces an earlier export: "
                         "choose another folder")
    for earlier in folder.iterdir():  # split folders, or agent folders of the older layout
        shutil.rmtree(earlier)


def agent_folder_names(state: WorldState) -> list[str]:
    """Folder names of the agents (agent order): ``+<id>`` for cav_0, the other CAVs' object
    ids, RSUs ``-1, -2, ...`` (module docstring: OpenCOOD's ego is then cav_0)."""
    n_cav = state.agent_kinds.count("cav")  # CAVs come first (WorldState contract)
    names = [str(oid) for oid in state.agent_object_ids[:n_cav].tolist()]
    names[:1] = [f"+{name}" for name in names[:1]]
    return names + [str(-(k + 1)) for k in range(state.num_agents - n_cav)]


def export_opv2v(states: Sequence[WorldState], folder: str | Path, overwrite: bool = False,
                 split: str = DEFAULT_SPLIT, scenario: str = DEFAULT_SCENARIO) -> list[Path]:
    """Write ``states`` (one per frame) under ``folder/split/scenario``; returns the agent
    folders written.

    A non-empty ``folder`` is refused unless ``overwrite``, which replaces an
    earlier export there (and refuses a folder holding anything else).
    """
    if not states:
        raise ValueError("states must contain at least one WorldState to export")
    prepare_export_folder(folder, overwrite)
    first = states[0]
    root = scenario_folder(folder, split, scenario)
    names = agent_folder_names(first)
    for index, state in enumerate(states):
        if state.agent_ids != first.agent_ids:
            raise ValueError(f"states[{index}] has agents {state.agent_ids}, states[0] has "
                             f"{first.agent_ids}; the agent set must stay constant")
        for name, data in zip(names, _agent_files(state), strict=True):
            path = root / name / f"{index:06d}.yaml"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(yaml.dump(data, Dumper=_Dumper, sort_keys=False))
    return [root / name for name in names]


def _agent_files(state: WorldState) -> list[dict]:
    """The label file contents of every agent (agent order) for one frame."""
    speed = np.hypot(*state.object_velocities.T) * 3.6
    objects = {
        int(oid): {
            "location": [float(box[0]), float(-box[1]), 0.0],
            "center": [0.0, 0.0, float(box[2])],
            "angle": [0.0, float(-np.rad2deg(box[6])), 0.0],
            "extent": [float(box[3] / 2), float(box[4] / 2), float(box[5] / 2)],
            "speed": float(kmh),
            "obj_type": OBJECT_CLASSES[int(cls)],
        }
        for oid, box, kmh, cls in zip(state.object_ids, state.object_boxes, speed,
                                      state.object_classes, strict=True)
    }
    files = []
    for a, kind in enumerate(state.agent_kinds):
        x, y, yaw = state.agent_poses[a]
        own = int(state.agent_object_ids[a]) if kind == "cav" else None
        ground = float(state.ground_heights[a])
        lidar_z = ground + float(state.sensor_heights[a])
        data: dict = {}
        if kind == "rsu":
            data["ego_speed"] = 0.0
        elif own in objects:
            data["ego_speed"] = objects[own]["speed"]
        data["lidar_pose"] = _carla_pose(x, y, lidar_z, yaw)
        data["true_ego_pos"] = _carla_pose(x, y, ground if kind == "cav" else lidar_z, yaw)
        data["vehicles"] = {oid: obj for oid, obj in objects.items() if oid != own}
        files.append(data)
    return files
