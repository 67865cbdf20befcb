"""Bring-your-own scene: a traffic source replaying the user's per-step arrays.

Usage::

    from roco_env.traffic import make_traffic_source
    from roco_env.traffic.frames import Frame
    frames = [Frame(object_ids=ids_t, object_boxes=boxes_t, cav_object_ids=[7, 12],
                    rsu_poses=[[0.0, 15.0, -1.57]]) for ids_t, boxes_t in my_data]
    config = load_scenario("urban_intersection", cavs=2, rsus=1,  # agents as in the frames
                           **{"traffic.source": "frames"})
    source = make_traffic_source(config, frames=frames)

Boxes are world-frame (x, y, z, l, w, h, yaw) in metres/radians
(docs/conventions.md); the CAVs are objects named by id (their box gives the agent pose),
RSUs are fixed poses. Each ``step`` advances one frame (``dt`` is not used);
on the last frame ``finished`` turns True (the env then truncates the episode;
a further ``step`` holds the last frame).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from roco_env.geometry import validate_boxes
from roco_env.scenario import AgentsConfig, ScenarioConfig
from roco_env.traffic.agents import make_world
from roco_env.traffic.state import OBJECT_CLASSES, WorldState


@dataclass
class Frame:
    """One time step of a user's scene.

    object_ids (M,) unique ints, stable over frames; object_boxes (M, 7) world boxes;
    cav_object_ids (C,) ids of the objects that are CAVs (same in every frame);
    rsu_poses (R, 3) world (x, y, yaw); object_classes (M,) indices into
    OBJECT_CLASSES (default all "car"); object_velocities (M, 2) m/s (default 0);
    time in s (default: frame index * the source's dt).
    """

    object_ids: Sequence[int] | np.ndarray
    object_boxes: Sequence[Sequence[float]] | np.ndarray
    cav_object_ids: Sequence[int] | np.ndarray = ()
    rsu_poses: Sequence[Sequence[float]] | np.ndarray = field(default_factory=list)
    object_classes: Sequence[int] | np.ndarray | None = None
    object_velocities: Sequence[Sequence[float]] | np.ndarray | None = None
    time: float | None = None


class SequenceSource:
    """A traffic source stepping through a fixed list of WorldStates (replay, frames)."""

    def __init__(self, states: Sequence[WorldState]) -> None:
        if not states:
            raise ValueError("a replayed scene needs at least one frame; got none")
        agent_ids = states[0].agent_ids
        for k, state in enumerate(states):
            if state.agent_ids != agent_ids:
                raise ValueError(
                    f"frame {k} has agents {state.agent_ids}, frame 0 has {agent_ids}; "
                    "the agent set must stay constant"
                )
        self.states = list(states)
        self.index = 0

    @property
    def num_frames(self) -> int:
        return len(self.states)

    @property
    def finished(self) -> bool:
        return self.index >= len(self.states) - 1

    def reset(self, rng: np.random.Generator) -> WorldState:
        """Back to the first frame (a replay has no randomness; rng is unused)."""
        self.index = 0
        return self.states[0]

    def step(self, dt: float) -> WorldState:
        """Advance one frame (``dt`` is not used); hold the last one at the end."""
        self.index = min(self.index + 1, len(self.states) - 1)
        return self.states[self.index]


def frame_to_state(frame: Frame, agents: AgentsConfig, index: int,
                   default_dt: float = 0.1) -> WorldState:
    """Validate one Frame and turn it into a WorldState (errors name frames[index].field)."""
    where = f"frames[{index}]"
    if not isinstance(frame, Frame):
        raise ValueError(f"{where} must be a roco_env.traffic.frames.Frame (Frame(object_ids=..., "
                         f"object_boxes=..., ...)); got {type(frame).__name__}")
    boxes = validate_boxes(frame.object_boxes, f"{where}.object_boxes")
    ids = np.asarray(frame.object_ids, dtype=np.int64).reshape(-1)
    m = boxes.shape[0]
    if ids.shape != (m,) or np.unique(ids).size != m:
        raise ValueError(f"{where}.object_ids must be {m} unique integers (one per box); "
                         f"got shape {ids.shape}")
    classes = np.zeros(m, np.int64) if frame.object_classes is None else \
        np.asarray(frame.object_classes, dtype=np.int64).reshape(-1)
    if classes.shape != (m,) or np.any((classes < 0) | (classes >= len(OBJECT_CLASSES))):
        raise ValueError(f"{where}.object_classes must be {m} indices in "
                         f"0..{len(OBJECT_CLASSES) - 1} ({', '.join(OBJECT_CLASSES)})")
    vel = np.zeros((m, 2)) if frame.object_velocities is None else \
        np.asarray(frame.object_velocities, dtype=float)
    if vel.shape != (m, 2) or not np.all(np.isfinite(vel)):
        raise ValueError(f"{where}.object_velocities must be finite with shape ({m}, 2); "
                         f"got {vel.shape}")
    cav_ids = np.asarray(frame.cav_object_ids, dtype=np.int64).reshape(-1)
    missing = sorted(set(cav_ids.tolist()) - set(ids.tolist()))
    if missing:
        raise ValueError(f"{where}.cav_object_ids {missing} are not among its object_ids")
    lookup = {int(i): k for k, i in enumerate(ids)}
    rsus = np.asarray(frame.rsu_poses, dtype=float).reshape(-1, 3)
    if not np.all(np.isfinite(rsus)):
        raise ValueError(f"{where}.rsu_poses must be finite (x, y, yaw) rows")
    time = index * default_dt if frame.time is None else float(frame.time)
    return make_world(time, ids, classes, boxes, vel, [lookup[int(c)] for c in cav_ids], rsus,
                      agents)


class FramesSource(SequenceSource):
    """Traffic source over user frames (see the module docstring); ``dt`` (s) dates
    frames that carry no time."""

    def __init__(self, frames: Sequence[Frame], agents: AgentsConfig, dt: float = 0.1) -> None:
        super().__init__([frame_to_state(f, agents, k, dt) for k, f in enumerate(frames)])


def frames_source(config: ScenarioConfig, frames: Sequence[Frame] | None = None) -> FramesSource:
    """The ``frames`` traffic stage's factory: the user's frames, which it requires."""
    if frames is None:
        raise ValueError(
            "traffic.source='frames' needs your frames: pass frames=[Frame(...), ...] to "
            "roco_env.parallel_env / roco_env.env (or to make_traffic_source)")
    return FramesSource(frames, config.agents, config.traffic.dt)
