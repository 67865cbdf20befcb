"""Intelligent Driver Model (Treiber et al. 2000) car-following, vectorised.

Vehicles live on lanes (:mod:`roco_env.traffic.lanes`) at arclength ``s`` (m)
with speed ``v`` (m/s). Every lane is cyclic for car following: the front
vehicle of a lane follows the rear vehicle of the same lane across the wrap,
so re-entering vehicles never collide. Extra virtual obstacles (stop lines
at red lights) are passed as per-vehicle gaps. One step costs a sort plus a
few array operations for all vehicles together. Hand-written: the model is a
closed formula and no installed library integrates it for array inputs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class IDMParams:
    """IDM parameters: a_max, b (comfortable decel), b_max (hard decel bound) in m/s^2,
    time headway T (s), jam distance s0 (m), exponent delta."""

    a_max: float = 1.5
    b: float = 2.0
    b_max: float = 8.0
    headway: float = 1.2
    s0: float = 2.0
    delta: float = 4.0


def leaders(lane: np.ndarray, s: np.ndarray, lane_lengths: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """Index of each vehicle's leader on its lane and the centre-to-centre distance (m).

    A vehicle alone on its lane follows itself at one lane length.
    """
    n = s.shape[0]
    order = np.lexsort((s, lane))
    sorted_lane = lane[order]
    nxt = np.roll(np.arange(n), -1)
    # Wrap: the last vehicle of each lane group follows the first of the same group.
    group_start = np.flatnonzero(np.r_[True, sorted_lane[1:] != sorted_lane[:-1]])
    group_end = np.r_[group_start[1:], n] - 1
    nxt[group_end] = group_start
    leader = np.empty(n, dtype=np.int64)
    leader[order] = order[nxt]
    dist = np.mod(s[leader] - s, lane_lengths[lane])
    dist = np.where(leader == np.arange(n), lane_lengths[lane], dist)
    return leader, dist


def idm_acceleration(v: np.ndarray, v0: np.ndarray, gap: np.ndarray, dv: np.ndarray,
                     p: IDMParams) -> np.ndarray:
    """IDM acceleration (m/s^2) for speed v, desired speed v0, bumper gap (m), and
    approach rate dv = v - v_leader (m/s); bounded below by -b_max."""
    s_star = p.s0 + np.maximum(0.0, v * p.headway + v * dv / (2.0 * np.sqrt(p.a_max * p.b)))
    free = 1.0 - (v / np.maximum(v0, 1e-3)) ** p.delta
    acc = p.a_max * (free - (s_star / np.maximum(gap, 1e-2)) ** 2)
    return np.maximum(acc, -p.b_max)


def idm_step(lane: np.ndarray, s: np.ndarray, v: np.ndarray, lengths: np.ndarray,
             v0: np.ndarray, lane_lengths: np.ndarray, p: IDMParams, dt: float,
             stop_gap: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Advance all vehicles by ``dt`` seconds; returns new (s, v).

    lengths: vehicle lengths (m). stop_gap: optional per-vehicle distance (m)
    from the front bumper to a standing virtual obstacle (inf where none).
    Positions use the ballistic update with speeds clamped at zero.
    """
    leader, dist = leaders(lane, s, lane_lengths)
    gap = dist - 0.5 * (lengths + lengths[leader])
    dv = v - v[leader]
    if stop_gap is not None:
        closer = stop_gap < gap
        gap = np.where(closer, stop_gap, gap)
        dv = np.where(closer, v, dv)
    acc = idm_acceleration(v, v0, gap, dv, p)
    v_new = np.maximum(v + acc * dt, 0.0)
    ds = 0.5 * (v + v_new) * dt
    # Never move past the leader's rear bumper minus a safety margin (discrete-time guard).
    ds = np.minimum(ds, np.maximum(gap - 0.5, 0.0))
    return np.mod(s + ds, lane_lengths[lane]), v_new
