"""Tracks of one agent's boxes over its messages: where each object is going.

A late message shows moving objects where they were, not where they are; a receiver
that tracks each collaborator's boxes over its messages knows their velocities and can
move them to its own time, and knows which do not move (parked cars, stopped traffic),
which a delay cannot displace. :class:`BoxTracker` keeps constant-velocity Kalman
filters (filterpy; state x, vx, y, vy in the world frame, m and m/s) of one sender's box
centres:

* each message's centres (world frame, as the sender reports its pose) are matched to
  the tracks predicted to the message's instant by the Hungarian method on the squared
  Mahalanobis distance of the innovation, gated at ``gate`` (chi-square, 2 dof);
* a matched track is updated; an unmatched centre starts a track at rest with speed
  std ``initial_speed_std``; a track unmatched by more than ``max_missed`` messages in a
  row is dropped;
* process noise: white acceleration of std ``accel_std`` (filterpy's
  ``Q_discrete_white_noise``); measurement noise ``measurement_std`` per axis (box
  noise plus the sender's pose noise).

A track's velocity counts once it has ``min_hits`` measurements (one centre says
nothing about motion). :class:`KeyedTracks` keeps one tracker per (receiver, sender)
and feeds it each new message; :func:`moved_boxes` moves a message's boxes by their
velocities over its age. The env (``comm.compensation: track``) and the ``compensate``
policy wrapper both use them.
"""

from __future__ import annotations

import functools
from collections.abc import Hashable
from dataclasses import dataclass, field

import numpy as np
from filterpy.common import Q_discrete_white_noise
from filterpy.kalman import KalmanFilter
from scipy.optimize import linear_sum_assignment

from roco_env.schema import spec

__all__ = ["BoxTracker", "KeyedTracks", "TrackingParams", "moved_boxes", "world_centres"]

_H = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
_UNMATCHED = 1e9


@dataclass(frozen=True)
class TrackingParams:
    """The box tracks' filter (module docstring)."""

    measurement_std: float = spec(0.3, low=0.0, high=10.0, low_open=True,
                                  doc="std of a box centre as a measurement, m per axis")
    accel_std: float = spec(2.0, low=0.0, high=50.0, low_open=True,
                            doc="std of the white acceleration, m/s^2")
    initial_speed_std: float = spec(15.0, low=0.0, high=100.0, low_open=True,
                                    doc="speed std of a new track, m/s per axis")
    gate: float = spec(11.8, low=0.0, low_open=True, high=1000.0,
                       doc="association gate: squared Mahalanobis distance (chi-square, 2 dof; "
                       "11.8 keeps 99.7%)")
    max_missed: int = spec(2, low=0, high=100, doc="messages a track survives unmatched")
    min_hits: int = spec(2, low=2, high=100,
                         doc="measurements before a track's velocity counts")


@functools.lru_cache(maxsize=256)
def _motion(dt: float, accel_std: float) -> tuple[np.ndarray, np.ndarray]:
    """(F, Q) of a constant-velocity step of ``dt`` s (state x, vx, y, vy) with white
    acceleration of std ``accel_std`` m/s^2; read-only, shared by every track (messages
    come at a few distinct intervals)."""
    F = np.array([[1.0, dt, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0],
                  [0.0, 0.0, 1.0, dt], [0.0, 0.0, 0.0, 1.0]])
    Q = Q_discrete_white_noise(dim=2, dt=dt, var=accel_std ** 2, block_size=2)
    F.setflags(write=False)
    Q.setflags(write=False)
    return F, Q


@dataclass
class _Track:
    kf: KalmanFilter
    time: float
    hits: int = 1
    missed: int = 0


@dataclass
class BoxTracker:
    """Constant-velocity tracks of one sender's box centres (module docstring)."""

    params: TrackingParams = field(default_factory=TrackingParams)
    tracks: list[_Track] = field(default_factory=list)

    def _predicted(self, track: _Track, time: float) -> KalmanFilter:
        """``track``'s filter moved to ``time`` (s; no earlier than its last)."""
        dt = max(time - track.time, 0.0)
        if dt > 0.0:
            kf = track.kf
            kf.F, kf.Q = _motion(round(dt, 9), self.params.accel_std)
            kf.predict()
            track.time = time
        return track.kf

    def _new(self, centre: np.ndarray, time: float) -> _Track:
        p = self.params
        kf = KalmanFilter(dim_x=4, dim_z=2)
        kf.H, kf.R = _H.copy(), np.eye(2) * p.measurement_std ** 2
        kf.x = np.array([[centre[0]], [0.0], [centre[1]], [0.0]])
        kf.P = np.diag([p.measurement_std, p.initial_speed_std] * 2) ** 2
        return _Track(kf, time)

    def update(self, time: float, centres: np.ndarray) -> np.ndarray:
        """Feed one message: its instant ``time`` (s) and its box centres (n, 2), world
        frame (m). Returns each centre's track, an index into ``tracks`` (n,)."""
        centres = np.asarray(centres, dtype=float).reshape(-1, 2)
        filters = [self._predicted(track, time) for track in self.tracks]
        cost = np.full((len(filters), centres.shape[0]), _UNMATCHED)
        if filters:
            means = np.stack([kf.x[[0, 2], 0] for kf in filters])  # (T, 2)
            spread = np.stack([kf.P[np.ix_([0, 2], [0, 2])] + kf.R for kf in filters])
            innovation = centres[None, :, :] - means[:, None, :]  # (T, n, 2)
            distance = np.einsum("tni,tij,tnj->tn", innovation, np.linalg.inv(spread),
                                 innovation)
            cost = np.where(distance <= self.params.gate, distance, _UNMATCHED)
        rows, cols = linear_sum_assignment(cost)
        matched = {int(c): int(r) for r, c in zip(rows, cols, strict=True)
                   if cost[r, c] < _UNMATCHED}
        for row, track in enumerate(self.tracks):
            track.missed = 0 if row in matched.values() else track.missed + 1
        for col, row in matched.items():
            self.tracks[row].kf.update(centres[col].reshape(2, 1))
            self.tracks[row].hits += 1
        assigned = np.empty(centres.shape[0], dtype=np.int64)
        for col in range(centres.shape[0]):
            if col not in matched:
                self.tracks.append(self._new(centres[col], time))
            assigned[col] = matched.get(col, len(self.tracks) - 1)
        survivors = [k for k, t in enumerate(self.tracks) if t.missed <= self.params.max_missed]
        renumber = np.full(len(self.tracks), -1, dtype=np.int64)
        renumber[survivors] = np.arange(len(survivors))
        self.tracks = [self.tracks[k] for k in survivors]
        return renumber[assigned]  # a centre's own track was matched now: it survives

    def velocities(self, tracks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(velocity (n, 2) m/s in the world frame, known (n,) bool) of the given tracks;
        unknown (zero) before ``min_hits`` measurements."""
        tracks = np.asarray(tracks, dtype=np.int64).reshape(-1)
        velocity = np.zeros((tracks.shape[0], 2))
        known = np.zeros(tracks.shape[0], dtype=bool)
        for k, index in enumerate(tracks.tolist()):
            track = self.tracks[index]
            if track.hits >= self.params.min_hits:
                velocity[k] = track.kf.x[[1, 3], 0]
                known[k] = True
        return velocity, known


def world_centres(boxes: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Centres (n, 2) in the world of boxes (n, >=2) given in the frame of world pose (3,)."""
    boxes = np.asarray(boxes, dtype=float).reshape(len(boxes), -1)
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return np.stack([pose[0] + c * boxes[:, 0] - s * boxes[:, 1],
                     pose[1] + s * boxes[:, 0] + c * boxes[:, 1]], axis=1)


def moved_boxes(boxes: np.ndarray, pose: np.ndarray, velocity: np.ndarray,
                seconds: float) -> np.ndarray:
    """A copy of boxes (n, 7) given in the frame of world pose (3,) with their centres moved
    by ``velocity`` (n, 2) m/s (world frame) for ``seconds`` s; headings kept."""
    out = np.array(boxes, dtype=float)
    c, s = np.cos(pose[2]), np.sin(pose[2])
    shift = np.asarray(velocity, dtype=float).reshape(-1, 2) * seconds
    out[:, 0] += c * shift[:, 0] + s * shift[:, 1]
    out[:, 1] += -s * shift[:, 0] + c * shift[:, 1]
    return out


class KeyedTracks:
    """One :class:`BoxTracker` per key (a (receiver, sender) pair), fed each new message."""

    def __init__(self, params: TrackingParams) -> None:
        self.params = params
        self._trackers: dict[Hashable, BoxTracker] = {}
        self._rows: dict[Hashable, np.ndarray] = {}  # the newest message's track per box

    def reset(self) -> None:
        """Forget every track (a new episode)."""
        self._trackers.clear()
        self._rows.clear()

    def velocities(self, key: Hashable, boxes: np.ndarray, pose: np.ndarray, time: float,
                   new: bool) -> tuple[np.ndarray, np.ndarray]:
        """(velocity (n, 2) m/s world frame, known (n,) bool) of the boxes (n, >=2) of the
        message of ``key`` sent at ``time`` (s) by a sender at world ``pose`` (3,); a
        ``new`` message (or the key's first) is fed to its tracker first."""
        if new or key not in self._rows:
            tracker = self._trackers.setdefault(key, BoxTracker(self.params))
            self._rows[key] = tracker.update(time, world_centres(boxes, pose))
        return self._trackers[key].velocities(self._rows[key])
