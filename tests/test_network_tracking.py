"""The box tracks of roco_env.comm.tracking against filterpy: the batched constant-velocity
filter makes the same associations (exactly) and holds the same states, covariances and
velocities (to rounding) as one filterpy KalmanFilter per track, the tracker it replaced,
kept here as the reference. KeyedTracks refuses a held message that changed."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pytest
from conftest import assert_equal_to_rounding
from filterpy.common import Q_discrete_white_noise
from filterpy.kalman import KalmanFilter
from scipy.optimize import linear_sum_assignment

from roco_env.comm.tracking import BoxTracker, KeyedTracks, TrackingParams

_H = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])


@dataclass
class _Track:
    kf: KalmanFilter
    time: float
    hits: int = 1
    missed: int = 0


@dataclass
class _FilterpyTracker:
    """The reference: one filterpy KalmanFilter per track, associations as BoxTracker's."""

    params: TrackingParams = field(default_factory=TrackingParams)
    tracks: list[_Track] = field(default_factory=list)

    def _predicted(self, track: _Track, time: float) -> KalmanFilter:
        dt = max(time - track.time, 0.0)
        if dt > 0.0:
            step = round(dt, 9)
            track.kf.F = np.array([[1.0, step, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0],
                                   [0.0, 0.0, 1.0, step], [0.0, 0.0, 0.0, 1.0]])
            track.kf.Q = Q_discrete_white_noise(dim=2, dt=step, var=self.params.accel_std ** 2,
                                                block_size=2)
            track.kf.predict()
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
        centres = np.asarray(centres, dtype=float).reshape(-1, 2)
        filters = [self._predicted(track, time) for track in self.tracks]
        cost = np.full((len(filters), centres.shape[0]), 1e9)
        if filters:
            means = np.stack([kf.x[[0, 2], 0] for kf in filters])
            spread = np.stack([kf.P[np.ix_([0, 2], [0, 2])] + kf.R for kf in filters])
            innovation = centres[None, :, :] - means[:, None, :]
            distance = np.einsum("tni,tij,tnj->tn", innovation, np.linalg.inv(spread),
                                 innovation)
            cost = np.where(distance <= self.params.gate, distance, 1e9)
        rows, cols = linear_sum_assignment(cost)
        matched = {int(c): int(r) for r, c in zip(rows, cols, strict=True) if cost[r, c] < 1e9}
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
        return renumber[assigned]


def _messages(seed: int, count: int = 30):
    """(time s, centres (n, 2) m) of ``count`` messages of one sender: movers and parked
    cars seen with noise, some missed, clutter, irregular instants, one out of order."""
    rng = np.random.default_rng(seed)
    start = rng.uniform(-60.0, 60.0, (14, 2))
    velocity = rng.normal(0.0, 12.0, (14, 2)) * (rng.random((14, 1)) < 0.7)
    times = np.cumsum(rng.choice([0.1, 0.2, 0.3], count)) + rng.uniform(0.0, 0.04, count)
    times[count // 2] = times[count // 2 - 2]  # a late message, older than the last fed
    out = []
    for time in times:
        seen = rng.random(14) < 0.8
        centres = start[seen] + velocity[seen] * time + rng.normal(0.0, 0.2, (seen.sum(), 2))
        clutter = rng.uniform(-60.0, 60.0, (rng.integers(0, 3), 2))
        out.append((float(time), rng.permutation(np.concatenate([centres, clutter]))))
    return out


@pytest.mark.parametrize("seed", range(6))
def test_the_batched_filter_is_filterpys_to_rounding(seed):
    params = TrackingParams(gate=30.0 if seed % 2 else 11.8, max_missed=seed % 3)
    tracker, reference = BoxTracker(params), _FilterpyTracker(params)
    matched = 0
    for time, centres in _messages(seed):
        rows, expected = tracker.update(time, centres), reference.update(time, centres)
        np.testing.assert_array_equal(rows, expected)
        assert len(tracker.tracks) == len(reference.tracks)
        assert_equal_to_rounding(tracker.tracks.state,
                                 [t.kf.x[:, 0] for t in reference.tracks])
        assert_equal_to_rounding(tracker.tracks.covariance,
                                 [t.kf.P for t in reference.tracks])
        np.testing.assert_array_equal(tracker.tracks.hits, [t.hits for t in reference.tracks])
        np.testing.assert_array_equal(tracker.tracks.missed,
                                      [t.missed for t in reference.tracks])
        velocity, known = tracker.velocities(rows)
        np.testing.assert_array_equal(known, [reference.tracks[r].hits >= params.min_hits
                                              for r in expected])
        assert_equal_to_rounding(velocity, [t.kf.x[[1, 3], 0] * (t.hits >= params.min_hits)
                                            for t in (reference.tracks[r] for r in expected)],
                                 )
        matched += int((tracker.tracks.hits > 1).sum())
    assert matched > 50  # the sequences exercise updates, not only new tracks


def test_an_empty_message_and_an_empty_tracker():
    tracker = BoxTracker()
    assert tracker.update(0.0, np.zeros((0, 2))).shape == (0,)
    assert list(tracker.update(0.1, [[1.0, 2.0], [5.0, 5.0]])) == [0, 1]
    assert tracker.update(0.2, np.zeros((0, 2))).shape == (0,)
    assert list(tracker.tracks.missed) == [1, 1]


def test_a_held_message_that_changed_is_refused():
    tracks = KeyedTracks(TrackingParams())
    boxes, pose = np.array([[1.0, 2.0], [3.0, 4.0]]), np.zeros(3)
    tracks.velocities("key", boxes, pose, 0.0, new=True)
    tracks.velocities("key", boxes, pose, 0.0, new=False)  # the same message again
    with pytest.raises(ValueError, match="'key' has 1 boxes, but 2"):
        tracks.velocities("key", boxes[:1], pose, 0.0, new=False)
