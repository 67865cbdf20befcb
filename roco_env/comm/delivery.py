"""The network stage: which scan of each collaborator an ego holds, how old, how heavy.

Every step each agent sends its scan (its top-K boxes in its own true frame, with its
reported pose; the feature map too under intermediate fusion) to every agent in whose
communication range it is, one message per link, cut to ``comm.budget_bytes`` by
:func:`roco_env.comm.payload.fit_budget`. Each message draws its delay
(``comm.delay``) and whether it is lost (``comm.loss``); it reaches the ego at the
first frame at or after its arrival. The ego holds the newest scan it has received from
each collaborator (an older one arriving later, out of order, is dropped) and drops one
older than ``comm.max_age_ms``. With ``comm.compensation: track`` the ego tracks each
collaborator's boxes over its messages (:class:`roco_env.comm.tracking.KeyedTracks`,
from the reported poses: no truth) and moves them along their velocities to its own
time, for alignment and fusion alike. An ego's collaborator slots are the agents in its
communication range now, nearest first, whose scan it holds, at most
``max_collaborators``. The ground truth stays the ego's present.

Asynchronous sensors: with ``comm.sensor_offset_ms`` = o for agent j, j's sweep ends o
ms before the receiving ego's, so what j sends at time t is the world at t - o: each box
of its scan moves back along its object's true velocity (false positives stand still)
and j's true and reported poses along j's own, constant velocity over the offset,
headings kept (an offset is a fraction of a frame). An ego's own boxes are of its own
time.

Draws: the generator given to :meth:`Network.reset` (the episode's fourth child
stream) spawns one stream for the delays and one for the losses, so changing the loss
model leaves the delays alone.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from roco_env.comm.delay import DelayModel, frames_late
from roco_env.comm.loss import LossModel
from roco_env.comm.payload import fit_budget
from roco_env.comm.tracking import KeyedTracks, TrackingParams, moved_boxes
from roco_env.scenario import CommConfig, ScenarioConfig
from roco_env.schema import ConfigError
from roco_env.sensing import AgentDetections, select_collaborators
from roco_env.stages import checked_params, stage
from roco_env.traffic.state import WorldState

__all__ = ["Delivery", "Network", "NetworkStats", "Scan", "instant_inbox", "network_active",
           "received_maps"]


def network_active(config: CommConfig) -> bool:
    """Whether the network stage runs: any ``comm`` field differs from its default (with
    all defaults every message arrives at once, whole, and the env skips the stage)."""
    return config != CommConfig()


@dataclass(frozen=True)
class Scan:
    """What agent ``sender`` sent at ``step``, as it was sent.

    time: the instant its sweep shows, s since reset; reported_pose / true_pose (3,):
    its world poses at that instant (x m, y m, yaw rad); boxes (k, 7), uncertainty (k, 3),
    scores (k,) in its true frame then, object_ids (k,) the truth (never read by the
    ego's policy); features: its BEV features (features.enabled) or None; encoder_map:
    the feature map it sent, float32 numpy (C, h, w) (cells the budget left out zeroed),
    or None; n_bytes: the message's size.
    """

    sender: int
    step: int
    time: float
    reported_pose: np.ndarray
    true_pose: np.ndarray
    boxes: np.ndarray
    uncertainty: np.ndarray
    scores: np.ndarray
    object_ids: np.ndarray
    features: Any
    encoder_map: np.ndarray | None
    n_bytes: int


@dataclass(frozen=True)
class Delivery:
    """A collaborator's scan an ego uses now: its age (s) and whether it arrived this step."""

    scan: Scan
    age: float
    new: bool


@dataclass(frozen=True)
class NetworkStats:
    """One step's traffic per agent: time (s since reset); bytes_sent (A,) of the messages
    it sent this step (one per link, lost ones included); bytes_received (A,) of the
    messages that reached it this step; messages_lost (A,) of those sent to it this step;
    compensated: whether the slots' boxes were moved to the ego's time
    (``comm.compensation: track``)."""

    time: float
    bytes_sent: np.ndarray
    bytes_received: np.ndarray
    messages_lost: np.ndarray
    compensated: bool = False

    def info(self, agent: int) -> dict:
        """Agent ``agent``'s info entries."""
        return {"time": self.time, "bytes_sent": int(self.bytes_sent[agent]),
                "bytes_received": int(self.bytes_received[agent]),
                "messages_lost": int(self.messages_lost[agent]),
                "compensated": self.compensated}


def _stage(kind: str, config: CommConfig) -> Any:
    name = getattr(config, kind)
    checked_params(kind, name, getattr(config, f"{kind}_params"), where="comm")
    return stage(kind, name).load_factory()(config)


def _offsets(config: CommConfig, agent_ids: Sequence[str]) -> np.ndarray:
    """(A,) sensor offsets in s; a ConfigError for an agent id the scenario does not have."""
    unknown = sorted(set(config.sensor_offset_ms) - set(agent_ids), key=str)
    if unknown:
        raise ConfigError(f"comm.sensor_offset_ms.{unknown[0]}: no agent {unknown[0]!r} in this "
                          f"scenario; agents: {', '.join(agent_ids)}")
    return np.array([config.sensor_offset_ms.get(a, 0.0) / 1000.0 for a in agent_ids])


class Network:
    """The network stage of one scenario (module docstring); ``reset`` then ``exchange``
    once per step."""

    def __init__(self, config: ScenarioConfig, agent_ids: Sequence[str]) -> None:
        comm = config.comm
        self.delay: DelayModel = _stage("delay", comm)
        self.loss: LossModel = _stage("loss", comm)
        self.offsets = _offsets(comm, agent_ids)
        self.budget = comm.budget_bytes
        self.codec = comm.feature_codec
        self.max_age = comm.max_age_ms / 1000.0
        self.frame_s = config.traffic.dt
        self.max_collaborators = config.max_collaborators
        self.sends_maps = config.fusion.method == "intermediate"
        self.tracks = KeyedTracks(TrackingParams()) if comm.compensation == "track" else None
        self._rngs: tuple[np.random.Generator, np.random.Generator] | None = None
        self._pending: list[tuple[int, int, Scan]] = []  # (arrival step, receiver, scan)
        self._held: dict[tuple[int, int], Scan] = {}  # (receiver, sender) -> newest scan

    def reset(self, rng: np.random.Generator) -> None:
        """Start an episode: every buffer emptied, the delay and loss streams from ``rng``."""
        self._rngs = tuple(rng.spawn(2))
        self.loss.reset()
        if self.tracks is not None:
            self.tracks.reset()
        self._pending.clear()
        self._held.clear()

    def exchange(self, step: int, state: WorldState, reported: np.ndarray,
                 detections: Sequence[AgentDetections], features: Sequence | None,
                 encoder_maps: Any) -> tuple[list[list[Delivery]], NetworkStats]:
        """Send this step's scans, deliver what arrives, and return per ego the deliveries
        of its collaborator slots (nearest first) and the step's traffic.

        reported (A, 3): the reported poses; detections: per agent, top-K, true frame;
        features: per agent BEV features or None; encoder_maps: the learned detector's
        maps (sent under intermediate fusion) or None."""
        if self._rngs is None:
            raise ValueError("exchange() called before reset(rng)")
        delay_rng, loss_rng = self._rngs
        now = step * self.frame_s
        n_agents = state.num_agents
        scans = [self._scan(j, step, now, state, reported, detections[j],
                            None if features is None else features[j],
                            encoder_maps if self.sends_maps else None) for j in range(n_agents)]
        in_range = [select_collaborators(state, i, n_agents) for i in range(n_agents)]
        links = [(i, j) for i in range(n_agents) for j in in_range[i]]
        senders = np.array([j for _, j in links], dtype=np.int64)
        receivers = np.array([i for i, _ in links], dtype=np.int64)
        sizes = np.array([scans[j].n_bytes for j in senders.tolist()], dtype=np.int64)
        poses = state.agent_poses
        distances = np.hypot(*(poses[senders, :2] - poses[receivers, :2]).T) if links \
            else np.zeros(0)
        late = frames_late(self.delay.draw(delay_rng, sizes, distances, self.frame_s),
                           self.frame_s)
        lost = self.loss.lost(loss_rng, links)
        bytes_sent = np.bincount(senders, sizes, minlength=n_agents).astype(np.int64)
        messages_lost = np.bincount(receivers, lost, minlength=n_agents).astype(np.int64)
        self._pending += [(step + int(k), i, scans[j]) for (i, j), k, gone
                          in zip(links, late.tolist(), lost.tolist(), strict=True) if not gone]
        bytes_received = np.zeros(n_agents, dtype=np.int64)
        arrived = set()
        waiting = []
        for entry in self._pending:
            arrival, receiver, scan = entry
            if arrival > step:
                waiting.append(entry)
                continue
            bytes_received[receiver] += scan.n_bytes
            held = self._held.get((receiver, scan.sender))
            if held is None or scan.step > held.step:
                self._held[(receiver, scan.sender)] = scan
                arrived.add((receiver, scan.sender))
        self._pending = waiting
        self._held = {key: scan for key, scan in self._held.items()
                      if now - scan.time <= self.max_age + 1e-9}
        inbox = [[Delivery(self._held[(i, j)], now - self._held[(i, j)].time, (i, j) in arrived)
                  for j in in_range[i] if (i, j) in self._held][: self.max_collaborators]
                 for i in range(n_agents)]
        if self.tracks is not None:
            inbox = [[self._compensated(i, d) for d in received]
                     for i, received in enumerate(inbox)]
        return inbox, NetworkStats(now, bytes_sent, bytes_received, messages_lost,
                                   self.tracks is not None)

    def _compensated(self, receiver: int, delivery: Delivery) -> Delivery:
        """``delivery`` with its boxes moved to the receiver's time along their tracks
        (``comm.compensation: track``; a box whose track does not know its velocity yet
        stays)."""
        scan = delivery.scan
        velocity, _ = self.tracks.velocities((receiver, scan.sender), scan.boxes,
                                             scan.reported_pose, scan.time, delivery.new)
        boxes = moved_boxes(scan.boxes, scan.reported_pose, velocity, delivery.age)
        return dataclasses.replace(delivery, scan=dataclasses.replace(scan, boxes=boxes))

    def _scan(self, sender: int, step: int, now: float, state: WorldState, reported: np.ndarray,
              detections: AgentDetections, features: Any, encoder_maps: Any) -> Scan:
        """Agent ``sender``'s scan as it sends it: moved back by its sensor offset, cut to
        the budget."""
        offset = float(self.offsets[sender])
        boxes, true_pose, reported_pose = detections.boxes, state.agent_poses[sender], \
            reported[sender]
        if offset > 0.0:
            boxes, back = _earlier(detections, state, sender, offset)
            true_pose, reported_pose = true_pose - back, reported_pose - back
        sent_map = None if encoder_maps is None else \
            encoder_maps.maps[sender].detach().cpu().numpy()
        kept, sent_map, n_bytes = fit_budget(detections.scores, sent_map, self.codec,
                                             self.budget)
        return Scan(sender, step, now - offset, np.array(reported_pose, dtype=float),
                    np.array(true_pose, dtype=float), boxes[kept], detections.uncertainty[kept],
                    detections.scores[kept], detections.object_ids[kept], features, sent_map,
                    n_bytes)


def instant_inbox(state: WorldState, reported: np.ndarray, detections: Sequence[AgentDetections],
                  features: Sequence | None, max_collaborators: int) -> list[list[Delivery]]:
    """Per ego, its collaborators' scans of now, whole (the network off): the agents in its
    communication range, nearest first, at most ``max_collaborators``."""
    scans = [Scan(j, -1, state.time, reported[j], state.agent_poses[j], d.boxes, d.uncertainty,
                  d.scores, d.object_ids, None if features is None else features[j], None, 0)
             for j, d in enumerate(detections)]
    return [[Delivery(scans[j], 0.0, True)
             for j in select_collaborators(state, ego, max_collaborators)]
            for ego in range(state.num_agents)]


def _earlier(detections: AgentDetections, state: WorldState, sender: int,
             offset: float) -> tuple[np.ndarray, np.ndarray]:
    """(boxes, back): ``sender``'s boxes (k, 7) as of ``offset`` s earlier, in its true frame
    then, and ``back`` (3,), the world displacement (m, m, 0) taking its pose then to now."""
    velocity = np.zeros((detections.object_ids.shape[0], 2))
    known = detections.object_ids >= 0
    order = np.argsort(state.object_ids)
    rows = order[np.searchsorted(state.object_ids, detections.object_ids[known], sorter=order)]
    velocity[known] = state.object_velocities[rows]
    own = np.flatnonzero(state.object_ids == state.agent_object_ids[sender])
    own_velocity = state.object_velocities[own[0]] if own.size else np.zeros(2)
    shift = (velocity - own_velocity) * offset  # world motion relative to the sender
    yaw = state.agent_poses[sender, 2]
    cos, sin = np.cos(yaw), np.sin(yaw)
    boxes = detections.boxes.copy()
    boxes[:, 0] -= cos * shift[:, 0] + sin * shift[:, 1]
    boxes[:, 1] -= -sin * shift[:, 0] + cos * shift[:, 1]
    return boxes, np.array([*(own_velocity * offset), 0.0])


def received_maps(encoder_maps: Any, inbox: Sequence[Sequence[Delivery]]
                  ) -> tuple[Any, list[tuple[int, ...]]]:
    """The encoder maps intermediate fusion reads under the network: every agent's own map
    of now, then every delivered map, and per ego the rows of its slots' maps (a map left
    out by the budget is all zeros, which the maximum ignores)."""
    import torch

    maps = encoder_maps.maps
    rows, extra = [], []
    for deliveries in inbox:
        rows.append(tuple(range(maps.shape[0] + len(extra),
                                maps.shape[0] + len(extra) + len(deliveries))))
        extra += [torch.zeros_like(maps[0]) if d.scan.encoder_map is None else
                  torch.from_numpy(d.scan.encoder_map).to(maps.device) for d in deliveries]
    stacked = torch.cat([maps, torch.stack(extra)]) if extra else maps
    return dataclasses.replace(encoder_maps, maps=stacked), rows
