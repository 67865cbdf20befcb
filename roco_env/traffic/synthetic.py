"""Synthetic traffic sources (numpy only): IDM traffic on lanes and static parking.

Crowding knobs (``config.traffic``):
- ``density``: vehicles per 100 m of lane for lane layouts (capped by what
  fits with ``min_gap``); for ``parking_lot`` the fill ratio of the stalls in [0, 1].
- ``min_gap``: minimum bumper-to-bumper gap (m) at spawn and the IDM jam distance.
Vehicles that leave a lane's end re-enter at its start (the vehicle count and
the agent set stay constant). ``traffic_jam`` places queues with gaps in
[min_gap, min_gap + 2] m and modulates desired speeds with a travelling
stop-and-go wave. Vehicles of crossing lanes never overlap at spawn (the later
one is dropped). CAVs are vehicles near the scene centre chosen from the rng.
"""

from __future__ import annotations

import math

import numpy as np

from roco_env.geometry import bev_iou
from roco_env.scenario import ScenarioConfig
from roco_env.traffic.agents import make_world, rsu_poses, select_cavs
from roco_env.traffic.idm import IDMParams, idm_step, leaders
from roco_env.traffic.layouts import LaneLayout, ParkingLayout, build_layout
from roco_env.traffic.state import WorldState
from roco_env.traffic.vehicles import SPEED_FACTOR, sample_classes, sample_sizes

JAM_WAVE_PERIOD = 20.0  # s, period of the stop-and-go wave
JAM_WAVE_LENGTH = 150.0  # m, its wavelength along the lane
PARKING_MIX = np.array([0.85, 0.15, 0.0, 0.0])  # only cars and vans fit the stalls
NOSE_CLEARANCE = 0.3  # m between a parked car's front and the stall front line
STOP_DECEL = 6.0  # m/s^2: a vehicle that cannot stop at a red light with this decel drives on


def spawn_gaps(rng: np.random.Generator, lane_length: float, vehicle_lengths: np.ndarray,
               min_gap: float, queues: bool) -> np.ndarray:
    """Bumper-to-bumper gaps (m) behind each of the vehicles of one cyclic lane.

    The gaps fill the lane exactly (sum of lengths + gaps = lane_length) and are
    >= min_gap. Free flow spreads the slack at random; ``queues`` keeps gaps
    in [min_gap, min_gap + 2] and puts the remaining slack into a few open
    stretches between queues. The caller guarantees the vehicles fit.
    """
    n = vehicle_lengths.size
    slack = lane_length - vehicle_lengths.sum() - n * min_gap
    if not queues:
        return min_gap + slack * rng.dirichlet(np.ones(n))
    small = rng.uniform(0.0, 2.0, n)
    small *= min(1.0, slack / max(small.sum(), 1e-9))
    rest = slack - small.sum()
    openings = rng.choice(n, size=max(1, n // 12), replace=False)
    small[openings] += rest * rng.dirichlet(np.ones(openings.size))
    return min_gap + small


def _fit_count(lengths: np.ndarray, lane_length: float, min_gap: float) -> int:
    """How many of the vehicles (in order) fit on a cyclic lane with min_gap between them."""
    need = np.cumsum(lengths + min_gap)
    return int(np.searchsorted(need, lane_length, side="right"))


def _drop_overlaps(boxes: np.ndarray) -> np.ndarray:
    """Keep-mask dropping, from any pair of touching footprints, the later vehicle."""
    iou = np.triu(bev_iou(boxes, boxes), k=1)
    keep = np.ones(boxes.shape[0], dtype=bool)
    for i, j in zip(*np.nonzero(iou > 0.0), strict=True):
        if keep[i]:
            keep[j] = False
    return keep


class LaneTraffic:
    """IDM traffic on the lanes of a :class:`LaneLayout` (all layouts but parking_lot)."""

    def __init__(self, config: ScenarioConfig, layout: LaneLayout) -> None:
        self.config = config
        self.layout = layout
        self.queues = config.traffic.layout == "traffic_jam"
        self.idm = IDMParams(s0=config.traffic.min_gap)

    def _spawn_lane(self, rng: np.random.Generator, lane: int
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Arclengths, classes and sizes of the vehicles placed on one lane."""
        cfg, length = self.config.traffic, self.layout.lanes.lengths[lane]
        classes = sample_classes(rng, int(np.floor(cfg.density * length / 100.0)))
        sizes = sample_sizes(rng, classes)
        n = _fit_count(sizes[:, 0], length, cfg.min_gap)
        classes, sizes = classes[:n], sizes[:n]
        if n == 0:
            return np.zeros(0), classes, sizes
        gaps = spawn_gaps(rng, length, sizes[:, 0], cfg.min_gap, self.queues)
        step = 0.5 * sizes[:, 0] + gaps + 0.5 * np.roll(sizes[:, 0], -1)
        s = rng.uniform(0.0, length) + np.concatenate([[0.0], np.cumsum(step[:-1])])
        return np.mod(s, length), classes, sizes

    def reset(self, rng: np.random.Generator) -> WorldState:
        cfg, lanes = self.config.traffic, self.layout.lanes
        spawned = [self._spawn_lane(rng, lane) for lane in range(lanes.num_lanes)]
        self.lane = np.concatenate([np.full(s.size, k) for k, (s, _, _) in enumerate(spawned)])
        self.s = np.concatenate([s for s, _, _ in spawned])
        self.classes = np.concatenate([c for _, c, _ in spawned])
        self.sizes = np.concatenate([z for _, _, z in spawned])
        if self.s.size == 0:
            longest = float(np.max(lanes.lengths))
            # The smallest density whose floor(density * length / 100) is 1 on the longest
            # lane, rounded up to 3 decimals (100 / 300 m = 0.333 would still give 0).
            least = math.ceil(100.0 / longest * 1000.0) / 1000.0
            raise ValueError(
                f"traffic.density={cfg.density} places no vehicle on layout {cfg.layout!r}: a "
                f"lane holds floor(density * length / 100) vehicles and its longest lane is "
                f"{longest:.0f} m; use traffic.density >= {least:g} (vehicles per 100 m of "
                "lane) or a longer traffic.length"
            )
        keep = _drop_overlaps(self._boxes()) & ~self._in_box()
        self.lane, self.s = self.lane[keep], self.s[keep]
        self.classes, self.sizes = self.classes[keep], self.sizes[keep]
        n = self.s.size
        self.ids = np.arange(n, dtype=np.int64)
        self.v0 = self.layout.speed_limit * SPEED_FACTOR[self.classes] * rng.uniform(0.9, 1.1, n)
        self.time = 0.0
        self.signal_offset = rng.uniform(0.0, self.layout.signals.cycle) \
            if self.layout.signals is not None else 0.0
        self.wave_phase = rng.uniform(0.0, 2 * np.pi, lanes.num_lanes)
        self.v = self._initial_speed()
        boxes = self._boxes()
        self.cavs = select_cavs(rng, boxes[:, :2], np.zeros(2), self.config.agents.cavs,
                                self._cav_eligible(boxes))
        self.rsus = rsu_poses(self.layout.rsu_spots, self.config.agents.rsus, cfg.layout)
        return self._world(boxes)

    def step(self, dt: float) -> WorldState:
        if not dt > 0:
            raise ValueError(f"dt must be > 0 seconds; got {dt}")
        self.s, self.v = idm_step(self.lane, self.s, self.v, self.sizes[:, 0],
                                  self._desired_speed(), self.layout.lanes.lengths, self.idm,
                                  dt, self._stop_gap(self.v))
        self.time += dt
        return self._world(self._boxes())

    @property
    def num_vehicles(self) -> int:
        return int(self.s.size)

    def _cav_eligible(self, boxes: np.ndarray) -> np.ndarray:
        """Vehicles heading towards (or around) the scene centre, so CAVs stay near each
        other for a while; on straight roads also only the nearest vehicle's direction.
        Falls back to all vehicles when too few qualify."""
        heading = np.column_stack([np.cos(boxes[:, 6]), np.sin(boxes[:, 6])])
        radial = np.sum(boxes[:, :2] * heading, axis=1)
        eligible = radial <= 0.1 * np.hypot(boxes[:, 0], boxes[:, 1])
        if self.config.traffic.layout in ("highway", "traffic_jam") and eligible.any():
            pool = np.flatnonzero(eligible)
            nearest = pool[np.argmin(np.hypot(boxes[pool, 0], boxes[pool, 1]))]
            eligible &= heading @ heading[nearest] > 0.0
        if eligible.sum() < self.config.agents.cavs:
            return np.ones(boxes.shape[0], dtype=bool)
        return eligible

    def _initial_speed(self) -> np.ndarray:
        """Speeds compatible with the spawn gaps (IDM equilibrium-like, capped at v0)."""
        leader, dist = leaders(self.lane, self.s, self.layout.lanes.lengths)
        gap = dist - 0.5 * (self.sizes[:, 0] + self.sizes[leader, 0])
        stop = self._stop_gap(np.zeros(self.s.size), must_stop=True)
        if stop is not None:
            gap = np.minimum(gap, stop)
        v = np.clip((gap - self.idm.s0) / self.idm.headway, 0.0, self._desired_speed())
        return np.minimum(v, np.sqrt(2.0 * self.idm.b * np.maximum(gap, 0.0)))

    def _desired_speed(self) -> np.ndarray:
        if not self.queues:
            return self.v0
        phase = 2 * np.pi * (self.time / JAM_WAVE_PERIOD - self.s / JAM_WAVE_LENGTH)
        wave = 0.5 * (1.0 + np.sin(phase + self.wave_phase[self.lane]))
        return self.v0 * np.maximum(wave, 0.05)

    def _in_box(self) -> np.ndarray:
        """Vehicles whose footprint reaches into the signalled shared box."""
        signals = self.layout.signals
        if signals is None:
            return np.zeros(self.s.size, dtype=bool)
        half = 0.5 * self.sizes[:, 0]
        return (self.s + half > signals.stop_s[self.lane]) & \
            (self.s - half < signals.exit_s[self.lane])

    def _stop_gap(self, v: np.ndarray, must_stop: bool = False) -> np.ndarray | None:
        """Gap (m) to a closed stop line, inf where open. A line is closed on red (unless
        the vehicle at speed v cannot stop at STOP_DECEL any more) and whenever a vehicle
        of the crossing phase group occupies the box; ``must_stop`` ignores the
        cannot-stop exception."""
        signals = self.layout.signals
        if signals is None:
            return None
        group = signals.group[self.lane]
        red = signals.red(self.time + self.signal_offset)[self.lane]
        occupied = np.bincount(group[self._in_box()], minlength=2) > 0
        to_line = signals.stop_s[self.lane] - self.s - 0.5 * self.sizes[:, 0]
        can_stop = must_stop | (to_line >= v**2 / (2.0 * STOP_DECEL))
        closed = (red & can_stop) | occupied[1 - group]
        return np.where(closed & (to_line > 0.0), to_line, np.inf)

    def _boxes(self) -> np.ndarray:
        x, y, yaw = self.layout.lanes.pose(self.lane, self.s)
        h = self.sizes[:, 2]
        return np.column_stack([x, y, 0.5 * h, self.sizes[:, 0], self.sizes[:, 1], h, yaw])

    def _world(self, boxes: np.ndarray) -> WorldState:
        vel = self.v[:, None] * np.column_stack([np.cos(boxes[:, 6]), np.sin(boxes[:, 6])])
        return make_world(self.time, self.ids, self.classes, boxes, vel, self.cavs, self.rsus,
                          self.config.agents)


class ParkingLotTraffic:
    """Static rows of parked cars 2.5 m apart: the repetitive hard case for matching.

    ``density`` is the fill ratio of the stalls (values above 1 mean full).
    Cars park nose-in, their front ``NOSE_CLEARANCE`` m short of the stall front,
    with small jitter (5 cm, 1 deg) like real parking.
    """

    def __init__(self, config: ScenarioConfig, layout: ParkingLayout) -> None:
        self.config = config
        self.layout = layout

    def reset(self, rng: np.random.Generator) -> WorldState:
        stalls = self.layout.stalls
        fill = min(self.config.traffic.density, 1.0)
        occupied = np.flatnonzero(rng.random(stalls.shape[0]) < fill)
        n = occupied.size
        self.classes = sample_classes(rng, n, PARKING_MIX)
        sizes = sample_sizes(rng, self.classes)
        front = stalls[occupied]
        back = NOSE_CLEARANCE + 0.5 * sizes[:, 0]
        yaw = front[:, 2] + rng.normal(0.0, np.deg2rad(1.0), n)
        centre = front[:, :2] - back[:, None] * np.column_stack([np.cos(yaw), np.sin(yaw)])
        centre += rng.normal(0.0, 0.05, (n, 2))
        boxes = np.column_stack([centre, 0.5 * sizes[:, 2], sizes, yaw])
        keep = _drop_overlaps(boxes)
        self.boxes, self.classes = boxes[keep], self.classes[keep]
        self.ids = np.arange(self.boxes.shape[0], dtype=np.int64)
        self.time = 0.0
        self.cavs = select_cavs(rng, self.boxes[:, :2], np.zeros(2), self.config.agents.cavs)
        self.rsus = rsu_poses(self.layout.rsu_spots, self.config.agents.rsus, "parking_lot")
        return self._world()

    def step(self, dt: float) -> WorldState:
        if not dt > 0:
            raise ValueError(f"dt must be > 0 seconds; got {dt}")
        self.time += dt
        return self._world()

    @property
    def num_vehicles(self) -> int:
        return int(self.ids.size)

    def _world(self) -> WorldState:
        return make_world(self.time, self.ids, self.classes, self.boxes,
                          np.zeros((self.ids.size, 2)), self.cavs, self.rsus, self.config.agents)


def make_synthetic(config: ScenarioConfig) -> LaneTraffic | ParkingLotTraffic:
    """Synthetic source for ``config.traffic.layout``."""
    layout = build_layout(config.traffic)
    if isinstance(layout, ParkingLayout):
        return ParkingLotTraffic(config, layout)
    return LaneTraffic(config, layout)
