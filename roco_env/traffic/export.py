"""Write any episode (a list of WorldStates) as OPV2V-format label folders.

Layout: ``<folder>/<agent id>/<frame:06d>.yaml`` with CARLA conventions
(left-handed: y -> -y, yaw -> -yaw, degrees). CAV folders are named by the
CAV's object id (>= 0, as in OPV2V where it is the CARLA actor id), RSU
folders ``-1, -2, ...`` (V2XSet style). Each file holds the agent's
``lidar_pose`` (sensor at its height above the ground under the agent),
``true_ego_pos`` (ground level; the RSU's equals its lidar pose), ``ego_speed`` (km/h), and ``vehicles``: every
object but the agent itself, with ``location`` = (x, y, 0), ``center`` =
(0, 0, z), ``angle`` = [0, yaw, 0], ``extent`` = half sizes, ``speed`` (km/h)
and ``obj_type`` (car/van/truck/bus). Reading it back with
:func:`roco_env.traffic.replay.load_opv2v` gives the same world (when at least
two agents exist, so every CAV is listed by another agent, and the CAVs' object
ids are in increasing order, the order in which the replay sorts CAV folders).
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


def _is_agent_folder(path: Path) -> bool:
    """An OPV2V agent folder: an integer name holding only ``*.yaml`` label files."""
    try:
        int(path.name)
    except ValueError:
        return False
    return path.is_dir() and all(p.is_file() and p.suffix == ".yaml" for p in path.iterdir())


def prepare_export_folder(folder: str | Path, overwrite: bool) -> None:
    """Make ``folder`` ready for a fresh export: refuse a non-empty one unless ``overwrite``.

    Overwriting removes only earlier exports' agent folders; anything else in the
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
    foreign = sorted(p.name for p in folder.iterdir() if not _is_agent_folder(p))
    if foreign:
        raise ValueError(f"export folder {folder} holds {foreign[:3]}, which are not OPV2V agent "
                         "folders; overwrite only replaces an earlier export: choose another "
                         "folder")
    for agent_folder in folder.iterdir():
        shutil.rmtree(agent_folder)


def export_opv2v(states: Sequence[WorldState], folder: str | Path,
                 overwrite: bool = False) -> list[Path]:
    """Write ``states`` (one per frame) under ``folder``; returns the agent folders written.

    A non-empty ``folder`` is refused unless ``overwrite``, which replaces an
    earlier export there (and refuses a folder holding anything else).
    """
    if not states:
        raise ValueError("states must contain at least one WorldState to export")
    folder = Path(folder)
    prepare_export_folder(folder, overwrite)
    first = states[0]
    n_cav = first.agent_kinds.count("cav")  # CAVs come first (WorldState contract)
    names = [str(oid) for oid in first.agent_object_ids[:n_cav].tolist()]
    names += [str(-(k + 1)) for k in range(first.num_agents - n_cav)]
    for index, state in enumerate(states):
        if state.agent_ids != first.agent_ids:
            raise ValueError(f"states[{index}] has agents {state.agent_ids}, states[0] has "
                             f"{first.agent_ids}; the agent set must stay constant")
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
        for a, name in enumerate(names):
            x, y, yaw = state.agent_poses[a]
            own = int(state.agent_object_ids[a])
            ego_speed = float(speed[state.object_ids == own][0]) if own >= 0 else 0.0
            ground = float(state.ground_heights[a])
            lidar_z = ground + float(state.sensor_heights[a])
            data = {
                "ego_speed": ego_speed,
                "lidar_pose": _carla_pose(x, y, lidar_z, yaw),
                "true_ego_pos": _carla_pose(x, y, ground if own >= 0 else lidar_z, yaw),
                "vehicles": {oid: obj for oid, obj in objects.items() if oid != own},
            }
            path = folder / name / f"{index:06d}.yaml"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(yaml.dump(data, Dumper=_Dumper, sort_keys=False))
    return [folder / name for name in names]
