"""Road layouts of the synthetic traffic: lane polylines, signals, RSU spots.

World frame of docs/conventions.md; metres and radians; right-hand traffic.
The scene centre is the origin. Every layout is a pure function of the
traffic config (no randomness): the rng only places vehicles on it.

- highway: ``lanes`` straight lanes per direction, ``length`` m long, 3 m median.
- traffic_jam: the highway geometry (jam behaviour is in the source).
- intersection: two crossing roads (``lanes`` per direction, straight-through
  lanes, ``length`` m each) with a two-phase traffic light at the centre box.
- roundabout: up to two circulating ring lanes (``lanes`` capped at 2) plus four
  single-lane arms whose traffic turns right around the ring's outer edge into
  the next arm (no conflicting paths, so no yielding logic is needed).
- parking_lot: rows of perpendicular stalls 2.5 m wide (static scene).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from roco_env.scenario import TrafficConfig
from roco_env.traffic.lanes import LaneSet, arc, build_lanes, smooth_corners, straight

LANE_WIDTH = 3.5  # m
ROUNDABOUT_LANE_WIDTH = 4.5  # m: wide enough for a 12 m bus sweeping a curve
STALL_WIDTH = 2.5  # m, centre-to-centre spacing of parked cars
STALL_DEPTH = 5.5  # m
AISLE_WIDTH = 7.0  # m
DEFAULT_SPEED = {"highway": 30.0, "traffic_jam": 8.0, "intersection": 13.9, "roundabout": 9.0}


@dataclass(frozen=True)
class Signals:
    """Two-phase traffic light: per lane the stop-line arclength and the arclength where
    the lane leaves the shared box (m), and the phase group (0 or 1). Group 0 is
    green for ``green`` s, then all red for ``clearance`` s, then group 1 green,
    then all red again."""

    stop_s: np.ndarray
    exit_s: np.ndarray
    group: np.ndarray
    green: float = 15.0
    clearance: float = 5.0

    @property
    def cycle(self) -> float:
        return 2.0 * (self.green + self.clearance)

    def red(self, time: float) -> np.ndarray:
        """Per lane: True where the light is red (or all-red) at ``time`` s."""
        phase = np.mod(time, self.cycle)
        start = np.where(self.group == 0, 0.0, self.green + self.clearance)
        return ~((phase >= start) & (phase < start + self.green))


@dataclass(frozen=True)
class LaneLayout:
    """A layout with moving traffic: lanes, speed limit (m/s), optional signals,
    ordered RSU spots (K, 3) poses."""

    name: str
    lanes: LaneSet
    speed_limit: float
    rsu_spots: np.ndarray
    signals: Signals | None = None


@dataclass(frozen=True)
class ParkingLayout:
    """Static parking: stalls (S, 3) = (x, y, yaw) of the stall's front-middle point and the
    heading of a car parked nose-in; ordered RSU spots (K, 3)."""

    name: str
    stalls: np.ndarray
    rsu_spots: np.ndarray


def _rotate(points: np.ndarray, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return points @ np.array([[c, s], [-s, c]])


def _facing_centre(points: np.ndarray) -> np.ndarray:
    points = np.asarray(points, dtype=float)
    yaw = np.arctan2(-points[:, 1], -points[:, 0])
    return np.column_stack([points, yaw])


def highway(cfg: TrafficConfig) -> LaneLayout:
    half = cfg.length / 2.0
    offsets = 1.5 + (np.arange(cfg.lanes) + 0.5) * LANE_WIDTH
    lines = [straight((-half, -d), (half, -d)) for d in offsets]  # eastbound, south side
    lines += [straight((half, d), (-half, d)) for d in offsets]  # westbound, north side
    side = 1.5 + cfg.lanes * LANE_WIDTH + 3.0
    xs = np.array([0.0, 120.0, -120.0, 240.0])
    spots = np.column_stack([xs, np.full(xs.size, side), np.full(xs.size, -np.pi / 2)])
    speed = cfg.speed_limit or DEFAULT_SPEED[cfg.layout]
    return LaneLayout(cfg.layout, build_lanes(lines), speed, spots)


def intersection(cfg: TrafficConfig) -> LaneLayout:
    half = cfg.length / 2.0
    offsets = (np.arange(cfg.lanes) + 0.5) * LANE_WIDTH
    box = cfg.lanes * LANE_WIDTH
    lines, groups = [], []
    for d in offsets:
        lines += [straight((-half, -d), (half, -d)), straight((half, d), (-half, d))]
        lines += [straight((d, -half), (d, half)), straight((-d, half), (-d, -half))]
        groups += [0, 0, 1, 1]
    stop = np.full(len(lines), half - box - 1.5)
    exit_ = np.full(len(lines), half + box + 1.5)
    corner = box + 4.0
    spots = _facing_centre([[corner, corner], [-corner, -corner], [-corner, corner],
                            [corner, -corner]])
    speed = cfg.speed_limit or DEFAULT_SPEED["intersection"]
    return LaneLayout("intersection", build_lanes(lines), speed, spots,
                      Signals(stop_s=stop, exit_s=exit_, group=np.array(groups)))


def roundabout(cfg: TrafficConfig) -> LaneLayout:
    n = min(cfg.lanes, 2)
    width = ROUNDABOUT_LANE_WIDTH
    ring_radii = 14.0 + np.arange(n) * width
    outer_edge = ring_radii[-1] + width / 2
    arm = max(cfg.length / 2.0, outer_edge + 30.0)
    lines = [arc((0.0, 0.0), r, 0.0, 2 * np.pi) for r in ring_radii]
    d = 1.0 + 0.5 * width
    radius = outer_edge + 3.0 + 0.5 * width
    alpha = np.arcsin(d / radius)
    meet = np.sqrt(radius**2 - d**2)
    samples = max(2, int((arm - meet) / 4.0))
    for k in range(4):
        theta = k * np.pi / 2
        inbound = _rotate(np.array([[arm, d], [meet, d]]), theta)
        outbound = _rotate(np.array([[meet, -d], [arm, -d]]), theta + np.pi / 2)
        turn = arc((0.0, 0.0), radius, theta + alpha, theta + np.pi / 2 - alpha, 4.0)
        coarse = np.concatenate([np.linspace(inbound[0], inbound[1], samples), turn[1:-1],
                                 np.linspace(outbound[0], outbound[1], samples)])
        lines.append(smooth_corners(coarse, iterations=4))
    corner = radius + width + 6.0
    spots = np.vstack([[0.0, 0.0, 0.0], _facing_centre([[corner, corner], [-corner, -corner],
                                                         [-corner, corner], [corner, -corner]])])
    speed = cfg.speed_limit or DEFAULT_SPEED["roundabout"]
    return LaneLayout("roundabout", build_lanes(lines), speed, spots)


def parking_lot(cfg: TrafficConfig) -> ParkingLayout:
    """Double rows of stalls along x separated by aisles; ``lanes`` double rows,
    rows ``length`` m long (capped at 200 m)."""
    row_len = min(cfg.length, 200.0)
    per_row = int(row_len // STALL_WIDTH)
    xs = (np.arange(per_row) - (per_row - 1) / 2) * STALL_WIDTH
    pitch = 2 * STALL_DEPTH + AISLE_WIDTH
    stalls = []
    for r in range(cfg.lanes):
        y0 = (r - (cfg.lanes - 1) / 2) * pitch
        for yaw in (-np.pi / 2, np.pi / 2):  # the two stall rows, parked nose-in to the middle
            stalls.append(np.column_stack([xs, np.full(per_row, y0), np.full(per_row, yaw)]))
    aisle_y = ((np.arange(cfg.lanes + 1) - cfg.lanes / 2) * pitch)
    spots = np.column_stack([np.zeros(aisle_y.size), aisle_y, np.zeros(aisle_y.size)])
    order = np.argsort(np.abs(aisle_y), kind="stable")
    return ParkingLayout("parking_lot", np.concatenate(stalls), spots[order])


def build_layout(cfg: TrafficConfig) -> LaneLayout | ParkingLayout:
    """The layout named by ``cfg.layout`` (synthetic layouts only)."""
    builders = {"highway": highway, "traffic_jam": highway, "intersection": intersection,
                "roundabout": roundabout, "parking_lot": parking_lot}
    if cfg.layout not in builders:
        raise ValueError(
            f"traffic.layout={cfg.layout!r} is not a synthetic layout; allowed: {sorted(builders)}"
        )
    return builders[cfg.layout](cfg)
