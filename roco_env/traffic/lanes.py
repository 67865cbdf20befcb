"""Lane geometry: polylines with arclength parametrisation, vectorised lookup.

A lane is a centreline polyline in the world frame (metres). Every lane is
resampled once at a fixed arclength step so that the pose at arclength ``s``
of many vehicles on many lanes is a table lookup plus a linear interpolation
(no per-vehicle Python loop). Lanes are traversed in the order of their
points; arclength ``s`` runs from 0 to the lane length and wraps around (a
vehicle leaving the end re-enters at the start, so the vehicle count stays
constant). Hand-written because no installed library offers a batched
"many points on many polylines" lookup; shapely is used as a test oracle only.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

RESAMPLE_STEP = 0.25  # metres between table samples


@dataclass(frozen=True)
class LaneSet:
    """All lanes of a layout as padded lookup tables.

    lengths (L,) lane lengths, m. table_xy (L, S, 2) resampled centreline
    points; table_heading (L, S) heading of the chord from sample k to k+1
    (radians, CCW from +x). polylines: the original vertices per lane.
    """

    lengths: np.ndarray
    table_xy: np.ndarray
    table_heading: np.ndarray
    polylines: tuple[np.ndarray, ...]
    step: float = RESAMPLE_STEP

    @property
    def num_lanes(self) -> int:
        return int(self.lengths.shape[0])

    def wrap(self, lane: np.ndarray, s: np.ndarray) -> np.ndarray:
        """Arclength wrapped into [0, length) of each vehicle's lane."""
        return np.mod(s, self.lengths[lane])

    def pose(self, lane: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World (x, y, heading) at arclength ``s`` (wrapped) on ``lane``; all (N,)."""
        s = self.wrap(lane, s)
        pos = s / self.step
        k = np.minimum(pos.astype(np.int64), self.table_xy.shape[1] - 2)
        frac = (pos - k)[:, None]
        xy = (1.0 - frac) * self.table_xy[lane, k] + frac * self.table_xy[lane, k + 1]
        return xy[:, 0], xy[:, 1], self.table_heading[lane, k]


def polyline_length(points: np.ndarray) -> float:
    """Total length (m) of a polyline (P, 2)."""
    return float(np.sum(np.hypot(*np.diff(points, axis=0).T)))


def _resample(points: np.ndarray, step: float, size: int) -> tuple[np.ndarray, np.ndarray]:
    seg = np.hypot(*np.diff(points, axis=0).T)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    s = np.minimum(np.arange(size) * step, cum[-1])
    xy = np.stack([np.interp(s, cum, points[:, 0]), np.interp(s, cum, points[:, 1])], axis=1)
    # Heading of each table chord; repeated past the end where samples coincide.
    d = np.diff(xy, axis=0)
    heading = np.arctan2(d[:, 1], d[:, 0])
    valid = np.hypot(d[:, 0], d[:, 1]) > 1e-9
    last = np.maximum.accumulate(np.where(valid, np.arange(valid.size), 0))
    heading = heading[last]
    return xy, np.concatenate([heading, heading[-1:]])


def build_lanes(polylines: Sequence[np.ndarray], step: float = RESAMPLE_STEP) -> LaneSet:
    """Tabulate lanes given as polylines (P_i, 2) in metres (at least 2 distinct points)."""
    if not polylines:
        raise ValueError("polylines must contain at least one lane")
    lines = []
    for i, line in enumerate(polylines):
        arr = np.asarray(line, dtype=float)
        if arr.ndim != 2 or arr.shape[1] != 2 or arr.shape[0] < 2:
            raise ValueError(f"polylines[{i}] must have shape (P>=2, 2); got {arr.shape}")
        lines.append(arr)
    lengths = np.array([polyline_length(p) for p in lines])
    if np.any(lengths <= step):
        raise ValueError(f"every lane must be longer than {step} m; lengths {lengths.tolist()}")
    size = int(np.ceil(lengths.max() / step)) + 2
    tables = [_resample(p, step, size) for p in lines]
    return LaneSet(
        lengths=lengths,
        table_xy=np.stack([t[0] for t in tables]),
        table_heading=np.stack([t[1] for t in tables]),
        polylines=tuple(lines),
        step=step,
    )


def straight(start: Sequence[float], end: Sequence[float]) -> np.ndarray:
    """A two-point polyline from ``start`` to ``end`` (m)."""
    return np.array([start, end], dtype=float)


def arc(center: Sequence[float], radius: float, start_angle: float, end_angle: float,
        max_step: float = 1.0) -> np.ndarray:
    """Circular arc polyline (radians; CCW when end_angle > start_angle)."""
    n = max(2, int(np.ceil(abs(end_angle - start_angle) * radius / max_step)) + 1)
    t = np.linspace(start_angle, end_angle, n)
    return np.stack([center[0] + radius * np.cos(t), center[1] + radius * np.sin(t)], axis=1)


def smooth_corners(points: np.ndarray, iterations: int = 3) -> np.ndarray:
    """Chaikin corner cutting: rounds polyline corners, keeps both end points."""
    pts = np.asarray(points, dtype=float)
    for _ in range(iterations):
        q = 0.75 * pts[:-1] + 0.25 * pts[1:]
        r = 0.25 * pts[:-1] + 0.75 * pts[1:]
        inner = np.empty((2 * q.shape[0], 2))
        inner[0::2], inner[1::2] = q, r
        pts = np.concatenate([pts[:1], inner[1:-1], pts[-1:]])
    return pts
