"""The per-step perception pipeline upstream of the policy: traffic -> noise -> sensing -> views.

Built from a :class:`~roco_env.scenario.ScenarioConfig`; the environment drives
it (``reset(rng)`` then ``advance()`` once per step) and gets a :class:`PerceptionFrame`:
the world, every agent's reported pose and detections, and each agent's
:class:`~roco_env.observation.EgoView` (what its observation holds). Each agent
transmits at most K = ``max_boxes`` boxes, its top-K by score; the ego keeps
the same top-K of its own. The attack stage (:mod:`roco_env.attacks`, scenario
section ``attack``) rewrites what attackers send honest egos. With ``noise.perturb_ego=False`` an ego's own pose
in its view is its true pose (its collaborators' stay noisy).
"""

from __future__ import annotations

import dataclasses
import time
from collections import defaultdict
from collections.abc import Sequence
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from typing import Any

import numpy as np

from roco_env import sensing
from roco_env.attacks import make_attack
from roco_env.comm import (
    Delivery,
    Network,
    NetworkStats,
    instant_inbox,
    network_active,
    received_maps,
)
from roco_env.geometry import canonical_axial_yaw, se2_inverse, se2_relative, transform_boxes
from roco_env.noise import make_pose_noise
from roco_env.observation import EgoView, top_k
from roco_env.scenario import ScenarioConfig
from roco_env.sensing import (
    AgentDetections,
    Message,
    Visibility,
    compute_visibility,
    make_detector,
    select_collaborators,
)
from roco_env.traffic import make_traffic_source
from roco_env.traffic.state import WorldState


class StageClock:
    """Accumulates wall time per named stage (seconds); a no-op unless ``enabled``."""

    def __init__(self, enabled: bool = False) -> None:
        self.enabled = enabled
        self.seconds: dict[str, float] = defaultdict(float)

    def measure(self, stage: str) -> AbstractContextManager:
        """Context manager timing one run of ``stage``."""
        return _Timed(self.seconds, stage) if self.enabled else nullcontext()


class _Timed(AbstractContextManager):
    def __init__(self, sink: dict[str, float], stage: str) -> None:
        self.sink, self.stage = sink, stage

    def __enter__(self) -> _Timed:
        self.start = time.perf_counter()
        return self

    def __exit__(self, *exc: object) -> None:
        self.sink[self.stage] += time.perf_counter() - self.start


@dataclass(frozen=True)
class PerceptionFrame:
    """One step's perception inputs.

    state: the world; reported_poses (A, 3): the noise model's output for every
    agent (world frame); visibility: who sees what; detections: per agent, top-K,
    in its true sensor frame; features: per agent (C, H, W) tensors or None;
    views: per agent, what its observation holds; footprints: per agent, its
    own vehicle's box (7,) in its true sensor frame (what late fusion keeps
    clear of collaborators' boxes), None for an RSU; encoder_maps: with the
    learned detector, every agent's encoder map on one feature grid
    (:class:`~roco_env.sensing.learned.model.EncoderMaps`: what intermediate fusion
    warps and decodes), else None.
    """

    state: WorldState
    reported_poses: np.ndarray
    visibility: Visibility
    detections: tuple[AgentDetections, ...]
    features: tuple | None
    views: tuple[EgoView, ...]
    footprints: tuple[np.ndarray | None, ...]
    encoder_maps: Any = None


class Pipeline:
    """Traffic, pose noise, detector and messages of one scenario."""

    def __init__(self, config: ScenarioConfig, clock: StageClock | None = None,
                 frames: Sequence | None = None) -> None:
        """frames: the user's scene for ``traffic.source='frames'`` (roco_env.traffic.frames)."""
        self.config = config
        self.clock = clock or StageClock()
        self.traffic = make_traffic_source(config, frames=frames)
        self.agent_ids: tuple[str, ...] = tuple(
            [f"cav_{i}" for i in range(config.agents.cavs)]
            + [f"rsu_{i}" for i in range(config.agents.rsus)]
        )
        self.noise = make_pose_noise(config.noise, self.agent_ids, config.traffic.dt)
        evaluation = config.evaluation
        self.detector = make_detector(config.detector,
                                      (tuple(evaluation.x_range), tuple(evaluation.y_range)))
        self.grid = (
            sensing.BevGrid(tuple(evaluation.x_range), tuple(evaluation.y_range),
                            config.features.resolution)
            if config.features.enabled else None
        )
        self.network = Network(config, self.agent_ids) if network_active(config.comm) else None
        self.attack = make_attack(config, self.agent_ids)
        self._rngs: tuple[np.random.Generator, np.random.Generator] | None = None
        self._step = 0

    @property
    def feature_shape(self) -> tuple[int, int, int] | None:
        """(C, H, W) of the BEV feature maps, None when features are off."""
        if self.grid is None:
            return None
        return (len(sensing.CHANNELS), self.grid.H, self.grid.W)

    def reset(self, rng: np.random.Generator) -> PerceptionFrame:
        """Start an episode: independent child streams for traffic, noise, sensing and the
        network and the attack (spawned after the others: theirs do not change)."""
        traffic_rng, noise_rng, sensing_rng, comm_rng = rng.spawn(4)
        self._rngs = (noise_rng, sensing_rng)
        self._step = 0
        if self.network is not None:
            self.network.reset(comm_rng)
        self.attack.reset(*rng.spawn(1))
        with self.clock.measure("traffic"):
            state = self.traffic.reset(traffic_rng)
        if state.agent_ids != self.agent_ids:
            cavs = sum(a.startswith("cav_") for a in state.agent_ids)
            raise ValueError(
                f"the traffic source produced agents {list(state.agent_ids)} but the scenario's "
                f"agents.cavs={self.config.agents.cavs} and agents.rsus={self.config.agents.rsus} "
                f"imply {list(self.agent_ids)}; give the overrides cavs={cavs}, "
                f"rsus={len(state.agent_ids) - cavs} to match"
            )
        self.noise.reset(noise_rng)
        return self._observe(state)

    @property
    def finished(self) -> bool:
        """True when the traffic has no frame after the current one (the end of a replay or
        of the user's frames); sources that simulate never finish."""
        return bool(getattr(self.traffic, "finished", False))

    def advance(self) -> PerceptionFrame:
        """Move the traffic one step (config.traffic.dt seconds) and observe it."""
        if self._rngs is None:
            raise ValueError("advance() called before reset(rng)")
        with self.clock.measure("traffic"):
            state = self.traffic.step(self.config.traffic.dt)
        self._step += 1
        return self._observe(state)

    def _observe(self, state: WorldState) -> PerceptionFrame:
        noise_rng, sensing_rng = self._rngs
        with self.clock.measure("noise"):
            reported = self.noise.perturb(state.agent_poses, noise_rng)
        with self.clock.measure("visibility"):
            visibility = compute_visibility(state)
        with self.clock.measure("detection"):
            raw, encoder_maps = self.detector.perceive(state, visibility, sensing_rng)
            detections = tuple(_top_k_detections(d, self.config.max_boxes) for d in raw)
        features = None
        if self.grid is not None:
            with self.clock.measure("features"):
                features = tuple(sensing.bev_features(visibility, a, self.grid)
                                 for a in range(state.num_agents))
        with self.clock.measure("messages"):
            stats, map_rows = None, None
            if self.network is None:
                inbox = instant_inbox(state, np.asarray(reported, dtype=float), detections,
                                      features, self.config.max_collaborators)
            else:
                inbox, stats = self.network.exchange(self._step, state, reported, detections,
                                                     features, encoder_maps)
                if self.network.sends_maps:
                    encoder_maps, map_rows = received_maps(encoder_maps, inbox)
            own = reported if self.noise.perturb_ego else state.agent_poses
            inbox = self._tampered(state, detections, own, inbox)
            views = self._views(state, reported, detections, features, inbox, stats, map_rows)
        return PerceptionFrame(state, reported, visibility, detections, features, views,
                               own_footprints(state), encoder_maps)

    def _views(self, state: WorldState, reported: np.ndarray,
               detections: tuple[AgentDetections, ...], features: tuple | None,
               inbox: list[list[Delivery]], stats: NetworkStats | None,
               map_rows: list[tuple[int, ...]] | None) -> tuple[EgoView, ...]:
        """Every agent's view of the scans in its inbox; the relative poses of all (ego,
        slot) pairs in one batch each. With the network on (``stats`` given) the views
        carry each slot's age and whether it is new, and the step's traffic."""
        slots = [tuple(d.scan.sender for d in received) for received in inbox]
        own = reported if self.noise.perturb_ego else state.agent_poses
        true = state.agent_poses
        collab_poses = [np.array([d.scan.reported_pose for d in received]).reshape(-1, 3)
                        for received in inbox]
        collab_true = [np.array([d.scan.true_pose for d in received]).reshape(-1, 3)
                       for received in inbox]
        counts = [len(s) for s in slots]
        egos = np.repeat(np.arange(state.num_agents), counts)
        reported_relative = se2_relative(own[egos],
                                         np.concatenate([np.zeros((0, 3)), *collab_poses]))
        true_relative = se2_relative(true[egos], np.concatenate([np.zeros((0, 3)), *collab_true]))
        start = np.concatenate([[0], np.cumsum(counts)]).tolist()
        axial = self.detector.axial_headings
        views = []
        for ego, (received, slot) in enumerate(zip(inbox, slots, strict=True)):
            mine, rows = detections[ego], slice(start[ego], start[ego + 1])
            sent = [d.scan for d in received]
            own_boxes, collab_boxes = mine.boxes, tuple(m.boxes for m in sent)
            if axial:  # one world-anchored heading convention for the ego and its inbox
                heading = float(own[ego][2])  # the ego's own (reported) heading
                own_boxes = _with_axial_yaw(own_boxes, heading)
                collab_boxes = tuple(_with_axial_yaw(b, heading + rel[2]) for b, rel in
                                     zip(collab_boxes, reported_relative[rows], strict=True))
            timing = {} if stats is None else {
                "collab_age": np.array([d.age for d in received], dtype=float),
                "collab_new": np.array([d.new for d in received], dtype=bool),
                "network": stats.info(ego),
                "collab_map_rows": None if map_rows is None else map_rows[ego],
                "in_range": tuple(select_collaborators(state, ego,
                                                       self.config.max_collaborators))}
            views.append(EgoView(
                agent=ego,
                pose=np.array(own[ego], dtype=float),
                boxes=own_boxes,
                uncertainty=mine.uncertainty,
                scores=mine.scores,
                object_ids=mine.object_ids,
                collaborators=slot,
                collab_poses=collab_poses[ego],
                reported_relative=reported_relative[rows],
                true_relative=true_relative[rows],
                collab_boxes=collab_boxes,
                collab_uncertainty=tuple(m.uncertainty for m in sent),
                collab_scores=tuple(m.scores for m in sent),
                collab_object_ids=tuple(m.object_ids for m in sent),
                features=None if features is None else features[ego],
                collab_features=None if features is None else tuple(m.features for m in sent),
                **timing,
            ))
        return tuple(views)


    def _tampered(self, state: WorldState, detections: tuple[AgentDetections, ...],
                  own: np.ndarray, inbox: list[list[Delivery]]) -> list[list[Delivery]]:
        """The inbox with every attacker's scan to an honest ego rewritten by the attack
        stage (the forged boxes' object ids with it); the inbox itself when nobody attacks.
        The attack forges with what it knows now, also a scan the network delivers late."""
        if not self.attack.attackers:
            return inbox
        messages = [[Message(self.agent_ids[d.scan.sender], d.scan.reported_pose, d.scan.boxes,
                             d.scan.uncertainty, d.scan.scores, d.scan.features)
                     for d in received] for received in inbox]
        forged, ids = self.attack.tamper(state, detections, own, messages,
                                         [[d.scan.object_ids for d in received]
                                          for received in inbox])
        return [[d if m is original else Delivery(dataclasses.replace(
                    d.scan, reported_pose=m.reported_pose, boxes=m.boxes,
                    uncertainty=m.uncertainty, scores=m.scores, object_ids=object_ids),
                    d.age, d.new)
                 for d, original, m, object_ids in zip(received, sent, out, row_ids, strict=True)]
                for received, sent, out, row_ids in zip(inbox, messages, forged, ids, strict=True)]


def _with_axial_yaw(boxes: np.ndarray, frame_yaw: float) -> np.ndarray:
    """A copy of boxes (K, 7) whose axial headings are put in the half-turn convention of
    :func:`roco_env.geometry.canonical_axial_yaw`, seen from a frame rotated by frame_yaw
    (the boxes' frame's heading in the world, as far as the ego knows it: anchoring the
    half-turn in the world keeps its edges on the diagonals, away from traffic on
    axis-aligned roads, whichever way an agent, an RSU say, faces)."""
    out = boxes.copy()
    out[:, 6] = canonical_axial_yaw(boxes[:, 6], frame_yaw)
    return out


def own_footprints(state: WorldState) -> tuple[np.ndarray | None, ...]:
    """Each agent's own vehicle box (7,) in its true sensor frame; None for an RSU."""
    rows, objects = np.nonzero(state.agent_object_ids[:, None] == state.object_ids[None, :])
    boxes = transform_boxes(state.object_boxes[objects], se2_inverse(state.agent_poses[rows]))
    footprints: list[np.ndarray | None] = [None] * state.num_agents
    for row, box in zip(rows.tolist(), boxes, strict=True):
        footprints[row] = box
    return tuple(footprints)


def _top_k_detections(detections: AgentDetections, k: int) -> AgentDetections:
    """The at most ``k`` highest-scoring detections (order kept)."""
    if detections.scores.shape[0] <= k:
        return detections
    idx = top_k(detections.scores, k)
    return AgentDetections(detections.boxes[idx], detections.uncertainty[idx],
                           detections.scores[idx], detections.object_ids[idx])
