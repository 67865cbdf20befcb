"""highway-env scenes (highway, merge, roundabout, intersection) as a traffic source.

The scene runs headless (``render_mode=None``, SDL dummy video driver) and is
stepped with the IDLE meta-action, so every vehicle follows highway-env's own
IDM/MOBIL behaviour. Conversions at this boundary only (docs/conventions.md):

- highway-env's y axis points right (left-handed screen frame): world y = -y,
  world yaw = -heading, world velocity = (vx, -vy).
- Vehicles have no ids: stable integer ids are kept in a dict keyed by the
  object identity ``id(vehicle)`` (the entry holds the vehicle, so an id cannot
  be recycled while it is in use; entries of removed vehicles are dropped).
- Sizes are the vehicle's LENGTH x WIDTH with a 1.5 m height; class "car".
- CAVs: the controlled vehicles (``controlled_vehicles = agents.cavs`` where the
  scene supports it, i.e. highway and intersection). Merge and roundabout have
  one ego; further CAVs are the other vehicles nearest to it, chosen from the rng.
- Object set may change (the intersection scene spawns and removes vehicles);
  the agent set never does. highway-env keeps crashed controlled vehicles on
  the road (stopped), so their CAV stays. Should a CAV's vehicle ever leave
  ``road.vehicles``, it stays an object frozen at its last box with zero speed.
- RSUs stand at fixed road-side spots (scene dependent), ``agents.rsu_height``.
- The intersection scene writes IDM parameters on the vehicle *class*
  (process-wide). Every call into the scene runs inside a guard that installs
  this scene's class attributes and restores the previous ones afterwards.
- ``density`` sets ``vehicles_count`` (highway: density x lanes x length / 100)
  and ``initial_vehicle_count`` (intersection: 4 x density); merge and
  roundabout are fixed scenes. ``traffic.params`` is merged into the env config.
"""

from __future__ import annotations

import contextlib
import os
import warnings
from collections.abc import Iterator
from typing import Any

import numpy as np

from roco_env.geometry import wrap_angle
from roco_env.scenario import SOURCE_LAYOUTS, ScenarioConfig
from roco_env.traffic.agents import make_world, rsu_poses, select_cavs
from roco_env.traffic.state import WorldState

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")

# highway-env's scene per layout (the layouts are SOURCE_LAYOUTS["highway_env"]).
ENV_IDS = {layout: f"{layout}-v0" for layout in SOURCE_LAYOUTS["highway_env"]}
MULTI_CONTROLLED = ("highway", "intersection")
VEHICLE_HEIGHT = 1.5  # m, highway-env vehicles are 2D
# Road-side RSU spots in highway-env's own frame (x, y_right, heading): mirrored like vehicles.
_RSU_SPOTS_HE = {
    "highway": [[100.0, -6.0, 1.5708], [300.0, -6.0, 1.5708]],
    "merge": [[230.0, -6.0, 1.5708], [380.0, -6.0, 1.5708]],
    "roundabout": [[0.0, 0.0, 0.0], [30.0, -30.0, 2.356]],
    "intersection": [[12.0, 12.0, -2.356], [-12.0, -12.0, 0.785]],
}


def he_to_world(x: np.ndarray, y: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """highway-env (x, y right, heading clockwise) -> world (x, y left, yaw CCW), (N, 3)."""
    yaw = wrap_angle(-np.asarray(heading, dtype=float))
    return np.column_stack([x, -np.asarray(y, dtype=float), yaw])


def _vehicle_classes() -> list[type]:
    """Every class defined in highway-env's vehicle package (whose class-level
    parameters a scene may overwrite)."""
    import importlib
    import pkgutil

    import highway_env.vehicle as package

    classes = []
    for info in pkgutil.iter_modules(package.__path__):
        module = importlib.import_module(f"{package.__name__}.{info.name}")
        classes += [obj for obj in vars(module).values()
                    if isinstance(obj, type) and obj.__module__ == module.__name__]
    return classes


def _class_attrs(classes: list[type]) -> dict[type, dict[str, Any]]:
    return {cls: {k: v for k, v in vars(cls).items() if k.isupper()} for cls in classes}


def _set_class_attrs(snapshot: dict[type, dict[str, Any]]) -> None:
    for cls, attrs in snapshot.items():
        for key in [k for k in vars(cls) if k.isupper() and k not in attrs]:
            delattr(cls, key)
        for key, value in attrs.items():
            setattr(cls, key, value)


class HighwayEnvSource:
    """Traffic from a highway-env scene (see the module docstring)."""

    def __init__(self, config: ScenarioConfig) -> None:
        cfg = config.traffic
        if cfg.layout not in ENV_IDS:
            raise ValueError(f"traffic.layout={cfg.layout!r} is not a highway-env scene; "
                             f"allowed: {sorted(ENV_IDS)}")
        if config.agents.cavs < 1:
            raise ValueError("agents.cavs must be >= 1 for highway_env (the ego is a CAV)")
        import gymnasium
        import highway_env  # noqa: F401  (registers the scenes)

        self.config = config
        self.layout = cfg.layout
        self.frequency = int(round(1.0 / cfg.dt))
        self._guarded = _vehicle_classes()
        self._scene_attrs = _class_attrs(self._guarded)
        # highway-env resets (and may mutate classes) in its constructor. The v0 scenes are
        # the classic ones this adapter targets; gymnasium flags them as superseded.
        with self._scene(), warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*is out of date.*")
            self.env = gymnasium.make(ENV_IDS[cfg.layout], config=self._env_config(),
                                      render_mode=None)
        self._ids: dict[int, tuple[int, Any]] = {}
        self._next_id = 0
        self._last_box: dict[int, np.ndarray] = {}
        self._idle = 1

    def _env_config(self) -> dict[str, Any]:
        cfg, cavs = self.config.traffic, self.config.agents.cavs
        env_config: dict[str, Any] = {
            "simulation_frequency": self.frequency,
            "policy_frequency": self.frequency,
            "duration": 10**6,
            "offroad_terminal": False,
        }
        if self.layout in MULTI_CONTROLLED:
            env_config["controlled_vehicles"] = cavs
        if self.layout == "highway":
            env_config["lanes_count"] = cfg.lanes
            env_config["vehicles_count"] = max(1, int(round(cfg.density * cfg.lanes
                                                            * cfg.length / 100.0)))
        if self.layout == "intersection":
            env_config["initial_vehicle_count"] = max(1, int(round(4 * cfg.density)))
        env_config.update(cfg.params)
        return env_config

    @contextlib.contextmanager
    def _scene(self) -> Iterator[None]:
        """Run with this scene's vehicle-class attributes; restore the outside ones after."""
        outside = _class_attrs(self._guarded)
        _set_class_attrs(self._scene_attrs)
        try:
            yield
        finally:
            self._scene_attrs = _class_attrs(self._guarded)
            _set_class_attrs(outside)

    def reset(self, rng: np.random.Generator) -> WorldState:
        seed = int(rng.integers(0, 2**31 - 1))
        with self._scene():
            self.env.reset(seed=seed)
        unwrapped = self.env.unwrapped
        self._ids.clear()
        self._next_id = 0
        self._last_box.clear()
        self._idle = unwrapped.action_type.actions_indexes["IDLE"]
        self.time = 0.0
        ids, boxes, _ = self._objects()
        controlled = [self._stable_id(v) for v in unwrapped.controlled_vehicles]
        cavs = controlled[: self.config.agents.cavs]
        missing = self.config.agents.cavs - len(cavs)
        if missing > 0:
            others = ~np.isin(ids, cavs)
            ego = boxes[np.searchsorted(ids, cavs[0]), :2]
            extra = select_cavs(rng, boxes[:, :2], ego, missing, others)
            cavs += ids[extra].tolist()
        self.cav_ids = np.array(cavs, dtype=np.int64)
        spots = he_to_world(*np.array(_RSU_SPOTS_HE[self.layout]).T)
        self.rsus = rsu_poses(spots, self.config.agents.rsus, self.layout)
        return self._world()

    def step(self, dt: float) -> WorldState:
        if not np.isclose(dt, 1.0 / self.frequency):
            raise ValueError(f"dt={dt} s does not match this highway-env scene's step "
                             f"{1.0 / self.frequency} s (traffic.dt)")
        with self._scene():
            self.env.step(self._idle)
        self.time += dt
        return self._world()

    def close(self) -> None:
        self.env.close()

    def _stable_id(self, vehicle: Any) -> int:
        entry = self._ids.get(id(vehicle))
        if entry is None or entry[1] is not vehicle:
            entry = (self._next_id, vehicle)
            self._next_id += 1
            self._ids[id(vehicle)] = entry
        return entry[0]

    def _objects(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        vehicles = list(self.env.unwrapped.road.vehicles)
        present = {id(v) for v in vehicles}
        ids = np.array([self._stable_id(v) for v in vehicles], dtype=np.int64)
        for key in [k for k in self._ids if k not in present]:
            del self._ids[key]
        if not vehicles:
            return ids, np.zeros((0, 7)), np.zeros((0, 2))
        pos = np.array([v.position for v in vehicles], dtype=float)
        heading = np.array([v.heading for v in vehicles], dtype=float)
        vel = np.array([v.velocity for v in vehicles], dtype=float)
        pose = he_to_world(pos[:, 0], pos[:, 1], heading)
        size = np.array([[v.LENGTH, v.WIDTH] for v in vehicles], dtype=float)
        boxes = np.column_stack([pose[:, :2], np.full(len(vehicles), VEHICLE_HEIGHT / 2), size,
                                 np.full(len(vehicles), VEHICLE_HEIGHT), pose[:, 2]])
        vel[:, 1] *= -1.0
        order = np.argsort(ids, kind="stable")
        return ids[order], boxes[order], vel[order]

    def _world(self) -> WorldState:
        ids, boxes, vel = self._objects()
        present = np.isin(self.cav_ids, ids)
        for cav in self.cav_ids[present].tolist():
            self._last_box[cav] = boxes[np.searchsorted(ids, cav)]
        lost = self.cav_ids[~present].tolist()
        if lost:  # a CAV's vehicle left the scene: keep it frozen at its last box
            ids = np.r_[ids, lost]
            boxes = np.vstack([boxes, [self._last_box[c] for c in lost]])
            vel = np.vstack([vel, np.zeros((len(lost), 2))])
            order = np.argsort(ids, kind="stable")
            ids, boxes, vel = ids[order], boxes[order], vel[order]
        rows = np.searchsorted(ids, self.cav_ids)
        return make_world(self.time, ids, np.zeros(ids.size, np.int64), boxes, vel, rows,
                          self.rsus, self.config.agents)
