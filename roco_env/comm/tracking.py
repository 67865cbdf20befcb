"""Tracks of one agent's boxes over its messages: where each object is going.

A late message shows moving objects where they were, not where they are; a receiver
that tracks each collaborator's boxes over its messages knows their velocities and can
move them to its own time, and knows which do not move (parked cars, stopped traffic),
which a delay cannot displace. :class:`BoxTracker` keeps constant-velocity Kalman
filters (state x, vx, y, vy in the world frame, m and m/s) of one sender's box centres,
all its tracks in arrays (:class:`TrackSet`) predicted and updated in one batch:

* each message's centres (world frame, as the sender reports its pose) are matched to
  the tracks predicted to the message's instant by the Hungarian method on the squared
  Mahalanobis distance of the innovation, gated at ``gate`` (chi-square, 2 dof);
* a matched track is updated (the Kalman update with the Joseph form of the
  covariance); an unmatched centre starts a track at rest with speed std
  ``initial_speed_std``; a track unmatched by more than ``max_missed`` messages in a
  row is dropped;
* process noise: white acceleration of std ``accel_std`` (the discrete white noise
  model: per axis var * [[dt^4/4, dt^3/2], [dt^3/2, dt^2]]); measurement noise
  ``measurement_std`` per axis (box noise plus the sender's pose noise).

These are filterpy's ``KalmanFilter.predict`` / ``update`` and ``Q_discrete_white_noise``
equations, batched over the tracks (tests/test_network_tracking.py keeps a filterpy
tracker as the reference: the same associations, states equal to rounding).

A track's velocity counts once it has ``min_hits`` measurements (one centre says
nothing about motion). :class:`KeyedTracks` keeps one tracker per (receiver, sender)
and feeds it each new message; :func:`moved_boxes` moves a message's boxes by their
velocities over its age. The env (``comm.compensation: track``) and the ``compensate``
policy wrapper both use them.
"""

from __future__ import annotations

from collections.abc import Hashable
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from roco_env.schema import spec

__all__ = ["BoxTracker", "KeyedTracks", "TrackSet", "TrackingParams", "moved_boxes",
           "world_centres"]

_POSITION = [0, 2]  # the measured components of the state (x, y)
_VELOCITY = [1, 3]
_UNMATCHED = 1e9
_I2, _I4 = np.eye(2), np.eye(4)
_I2.setflags(write=False)
_I4.setflags(write=False)


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


def _motion(dt: np.ndarray, accel_std: float) -> tuple[np.ndarray, np.ndarray]:
    """(F, Q), each (T, 4, 4), of constant-velocity steps of ``dt`` (T,) s (state x, vx,
    y, vy) with white acceleration of std ``accel_std`` m/s^2."""
    count = dt.shape[0]
    F = np.tile(_I4, (count, 1, 1))
    F[:, 0, 1] = F[:, 2, 3] = dt
    var = accel_std ** 2
    Q = np.zeros((count, 4, 4))
    for axis in (0, 2):
        Q[:, axis, axis] = 0.25 * dt ** 4 * var
        Q[:, axis, axis + 1] = Q[:, axis + 1, axis] = 0.5 * dt ** 3 * var
        Q[:, axis + 1, axis + 1] = dt ** 2 * var
    return F, Q


def _transposed(matrices: np.ndarray) -> np.ndarray:
    return np.swapaxes(matrices, -1, -2)


def _applied(matrices: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """(T, i) products of matrices (T, i, j) with vectors (T, j)."""
    return (matrices @ vectors[:, :, None])[:, :, 0]


@dataclass
class TrackSet:
    """T tracks as arrays: state (T, 4) (x m, vx m/s, y m, vy m/s, world frame),
    covariance (T, 4, 4), time (T,) s (the instant of the state), hits (T,) measurements
    so far, missed (T,) messages in a row without a match."""

    state: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    covariance: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    time: np.ndarray = field(default_factory=lambda: np.zeros(0))
    hits: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    missed: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def __len__(self) -> int:
        return self.state.shape[0]

    def select(self, rows: np.ndarray) -> TrackSet:
        """The tracks of ``rows`` (an index or bool array), in that order."""
        return TrackSet(self.state[rows], self.covariance[rows], self.time[rows],
                        self.hits[rows], self.missed[rows])

    def joined(self, other: TrackSet) -> TrackSet:
        """These tracks, then ``other``'s."""
        return TrackSet(*(np.concatenate([mine, theirs]) for mine, theirs in zip(
            (self.state, self.covariance, self.time, self.hits, self.missed),
            (other.state, other.covariance, other.time, other.hits, other.missed),
            strict=True)))


@dataclass
class BoxTracker:
    """Constant-velocity tracks of one sender's box centres (module docstring)."""

    params: TrackingParams = field(default_factory=TrackingParams)
    tracks: TrackSet = field(default_factory=TrackSet)

    def _predict(self, time: float) -> None:
        """Every track moved to ``time`` (s); a track whose state is of ``time`` or later
        stays."""
        tracks = self.tracks
        ahead = np.flatnonzero(tracks.time < time)
        if ahead.size == 0:
            return
        F, Q = _motion(np.round(time - tracks.time[ahead], 9), self.params.accel_std)
        tracks.state[ahead] = _applied(F, tracks.state[ahead])
        tracks.covariance[ahead] = F @ tracks.covariance[ahead] @ _transposed(F) + Q
        tracks.time[ahead] = time

    def _correct(self, rows: np.ndarray, centres: np.ndarray) -> None:
        """The Kalman update of the tracks ``rows`` (m,) with the centres (m, 2)."""
        tracks, R = self.tracks, _I2 * self.params.measurement_std ** 2
        P = tracks.covariance[rows]
        innovation = centres - tracks.state[rows][:, _POSITION]
        PHT = P[:, :, _POSITION]  # P H^T, (m, 4, 2)
        gain = PHT @ np.linalg.inv(PHT[:, _POSITION, :] + R)  # (m, 4, 2)
        tracks.state[rows] += _applied(gain, innovation)
        I_KH = np.tile(_I4, (rows.shape[0], 1, 1))
        I_KH[:, :, _POSITION] -= gain
        tracks.covariance[rows] = I_KH @ P @ _transposed(I_KH) + gain @ R @ _transposed(gain)
        tracks.hits[rows] += 1

    def _started(self, centres: np.ndarray, time: float) -> TrackSet:
        """New tracks at rest at ``centres`` (n, 2) of ``time`` s."""
        p, count = self.params, centres.shape[0]
        state = np.zeros((count, 4))
        state[:, _POSITION] = centres
        covariance = np.tile(np.diag([p.measurement_std, p.initial_speed_std] * 2) ** 2,
                             (count, 1, 1))
        return TrackSet(state, covariance, np.full(count, time),
                        np.ones(count, dtype=np.int64), np.zeros(count, dtype=np.int64))

    def update(self, time: float, centres: np.ndarray) -> np.ndarray:
        """Feed one message: its instant ``time`` (s) and its box centres (n, 2), world
        frame (m). Returns each centre's track, an index into ``tracks`` (n,)."""
        centres = np.asarray(centres, dtype=float).reshape(-1, 2)
        self._predict(time)
        tracks, n = self.tracks, centres.shape[0]
        cost = np.full((len(tracks), n), _UNMATCHED)
        if len(tracks):
            spread = tracks.covariance[:, _POSITION][:, :, _POSITION] \
                + _I2 * self.params.measurement_std ** 2
            innovation = centres[None, :, :] - tracks.state[:, None, _POSITION]  # (T, n, 2)
            distance = np.einsum("tni,tij,tnj->tn", innovation, np.linalg.inv(spread),
                                 innovation)
            cost = np.where(distance <= self.params.gate, distance, _UNMATCHED)
        rows, cols = linear_sum_assignment(cost)
        matched = cost[rows, cols] < _UNMATCHED
        rows, cols = rows[matched], cols[matched]
        tracks.missed += 1
        tracks.missed[rows] = 0
        self._correct(rows, centres[cols])
        unmatched = np.ones(n, dtype=bool)
        unmatched[cols] = False
        fresh = np.flatnonzero(unmatched)
        assigned = np.empty(n, dtype=np.int64)
        assigned[cols] = rows
        assigned[fresh] = len(tracks) + np.arange(fresh.size)
        tracks = tracks.joined(self._started(centres[fresh], time))
        survivors = np.flatnonzero(tracks.missed <= self.params.max_missed)
        renumber = np.full(len(tracks), -1, dtype=np.int64)
        renumber[survivors] = np.arange(survivors.size)
        self.tracks = tracks.select(survivors)
        return renumber[assigned]  # a centre's own track was matched now: it survives

    def velocities(self, tracks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(velocity (n, 2) m/s in the world frame, known (n,) bool) of the given tracks;
        unknown (zero) before ``min_hits`` measurements."""
        tracks = np.asarray(tracks, dtype=np.int64).reshape(-1)
        known = self.tracks.hits[tracks] >= self.params.min_hits
        velocity = np.where(known[:, None], self.tracks.state[tracks][:, _VELOCITY], 0.0)
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
        elif len(boxes) != self._rows[key].shape[0]:
            raise ValueError(
                f"KeyedTracks: the held message of {key!r} has {len(boxes)} boxes, but "
                f"{self._rows[key].shape[0]} when it was fed; a message that is not new must "
                "be the one fed last (a changed message must come with new=True)")
        return self._trackers[key].velocities(self._rows[key])
