"""Which objects each agent's LiDAR sees: range, occlusion and expected returns.

Model (all agents and objects at once, vectorised with numpy):

* **Rays.** Each agent casts ``n_rays = round(360 / azimuth_resolution_deg)``
  horizontal rays from its sensor origin; ray ``k`` points at azimuth
  ``k * 2*pi / n_rays`` in the agent's TRUE sensor frame (so the resolution is
  rounded to tile the circle exactly). Only the rays inside an object's
  angular span are generated (one (ray, object) *pair* per ray crossing a
  footprint), never a dense rays x footprints matrix.
* **Candidates.** Objects whose centre lies within ``sensor_range`` plus
  their half diagonal take part (as targets and occluders); the agent's own
  vehicle and any footprint containing the sensor are left out. An object is
  *in range* when its centre distance is at most ``sensor_range``; a ray only
  produces returns where it enters a footprint within range.
* **Heights** are measured from the ground under the agent
  (``state.ground_heights``; 0 for simulated scenes), so a recording whose
  world z is offset (DAIR-V2X at ~20 m) is seen as on flat ground.
* **Occlusion (2.5D).** Along each ray the pairs are sorted by entry
  distance. Every object in front of a target casts a vertical shadow: the
  line of sight from the sensor (height ``h``) over the occluder's top edge
  (height ``top_o`` at its entry or exit distance, whichever is higher)
  reaches height ``h + slope * d`` at the target's entry distance ``d``; the
  target is visible on that ray above ``max(bottom_t, shadow)`` up to its
  top. A ray's *vertical visible fraction* is that visible height over the
  target height. Occluders taller than the sensor hide everything behind
  them; lower ones only cut off the bottom of far targets. RSUs use an
  occlusion height of ``rsu_height_factor * sensor_height`` (1.0 = physical
  mast height; 0.0 = ground level, i.e. pure 2D occlusion), so the factor sets
  how well RSUs see over cars. CAVs always use their sensor height.
* **Visible fraction** of an object = sum over its rays of the vertical
  visible fraction / number of rays that cross its footprint (the unoccluded
  count). ``visible`` = in range, not self, fraction > ``min_fraction``.
* **Returns** (expected LiDAR points) = sum over the object's rays of the
  number of vertical beams of :class:`LidarModel` inside the visible
  elevation interval, times ``ray spacing / lidar horizontal resolution``.
  They fall with distance (smaller angles) and with occlusion.

Ray hits (entry points of visible pairs) and each ray's first-hit distance are
kept for the BEV features; both are derived on first access (``Visibility.hits``
/ ``ray_ranges``), so a pipeline without features never pays for them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from roco_env.geometry import box_corners_bev
from roco_env.traffic.state import WorldState

__all__ = ["LidarModel", "RayHits", "Visibility", "compute_visibility"]

# Slopes are clipped to +-_SLOPE_CLIP so a per-ray running maximum can be taken
# in one pass with a group offset (_GROUP_STRIDE > 2 * _SLOPE_CLIP).
_SLOPE_CLIP = 1.0e3
_GROUP_STRIDE = 4.0e3


@dataclass(frozen=True)
class LidarModel:
    """A spinning LiDAR (defaults: a 64-beam HDL-64-like sensor).

    channels: vertical beams, evenly spaced between fov_down_deg and fov_up_deg
    (degrees, elevation from horizontal); horizontal_resolution_deg: azimuth
    step of one beam (degrees).
    """

    channels: int = 64
    fov_up_deg: float = 2.0
    fov_down_deg: float = -24.8
    horizontal_resolution_deg: float = 0.2

    def __post_init__(self) -> None:
        if not isinstance(self.channels, int) or self.channels < 2:
            raise ValueError(f"LidarModel.channels must be an int >= 2; got {self.channels!r}")
        if not -90.0 <= self.fov_down_deg < self.fov_up_deg <= 90.0:
            raise ValueError(
                "LidarModel needs -90 <= fov_down_deg < fov_up_deg <= 90; "
                f"got fov_down_deg={self.fov_down_deg}, fov_up_deg={self.fov_up_deg}"
            )
        if not self.horizontal_resolution_deg > 0.0:
            raise ValueError(
                "LidarModel.horizontal_resolution_deg must be > 0; "
                f"got {self.horizontal_resolution_deg}"
            )

    @property
    def beam_spacing(self) -> float:
        """Vertical angle between adjacent beams, radians."""
        return np.deg2rad(self.fov_up_deg - self.fov_down_deg) / (self.channels - 1)


@dataclass(frozen=True)
class RayHits:
    """Entry points of the rays that see part of an object (P of them), sorted by agent,
    then ray, then entry distance.

    agent (P,) agent index; obj (P,) object index (into WorldState objects);
    ray (P,) ray index; x, y (P,) entry point in the agent's true sensor frame (m);
    top (P,) height of the highest visible point on that ray (m above the ground under the agent);
    returns (P,) expected LiDAR points on that ray.
    """

    agent: np.ndarray
    obj: np.ndarray
    ray: np.ndarray
    x: np.ndarray
    y: np.ndarray
    top: np.ndarray
    returns: np.ndarray


@dataclass(frozen=True)
class _RayPairs:
    """The cast (ray, object) pairs, sorted by agent, ray, then entry distance (P of them).

    agent, obj, ray (P,) indices; angle (P,) ray azimuth in the agent frame (rad);
    entry (P,) distance where the ray enters the footprint (m); top (P,) highest
    visible point (m); returns (P,) expected LiDAR points; ranges (A,) sensor
    ranges (m); n_rays rays per agent.
    """

    agent: np.ndarray
    obj: np.ndarray
    ray: np.ndarray
    angle: np.ndarray
    entry: np.ndarray
    top: np.ndarray
    returns: np.ndarray
    ranges: np.ndarray
    n_rays: int


@dataclass(frozen=True)
class Visibility:
    """What each of the A agents sees of the M objects.

    fraction (A, M): visible fraction in [0, 1] (0 when out of range or self).
    returns (A, M): expected LiDAR points on the object.
    visible (A, M) bool: in range, not the agent's own vehicle, fraction > min_fraction.
    distance (A, M): sensor-to-object-centre distance in BEV (m).
    azimuth_step: ray spacing, radians.
    ray_ranges and hits (properties, computed on first access): see below.
    """

    fraction: np.ndarray
    returns: np.ndarray
    visible: np.ndarray
    distance: np.ndarray
    azimuth_step: float
    _pairs: _RayPairs = field(repr=False)

    @cached_property
    def ray_ranges(self) -> np.ndarray:
        """(A, n_rays): distance to the first footprint along each ray (sensor range where
        nothing is hit), m; ray k at azimuth k * azimuth_step."""
        pairs = self._pairs
        ray_ranges = np.repeat(pairs.ranges[:, None], pairs.n_rays, axis=1)
        first = np.ones(pairs.agent.shape, dtype=bool)
        first[1:] = (pairs.agent[1:] != pairs.agent[:-1]) | (pairs.ray[1:] != pairs.ray[:-1])
        agent = pairs.agent[first]
        ray_ranges[agent, pairs.ray[first]] = np.minimum(pairs.entry[first], pairs.ranges[agent])
        return ray_ranges

    @cached_property
    def hits(self) -> RayHits:
        """Entry points of the rays that see part of an object (:class:`RayHits`)."""
        pairs = self._pairs
        seen = pairs.returns > 0.0
        angle, entry = pairs.angle[seen], pairs.entry[seen]
        return RayHits(
            agent=pairs.agent[seen], obj=pairs.obj[seen], ray=pairs.ray[seen],
            x=entry * np.cos(angle), y=entry * np.sin(angle),
            top=pairs.top[seen], returns=pairs.returns[seen],
        )


def _check_inputs(state: WorldState, azimuth_resolution_deg: float, rsu_height_factor: float,
                  min_fraction: float) -> None:
    ranges = np.asarray(state.sensor_ranges, dtype=float)
    if ranges.size and not np.all(np.isfinite(ranges) & (ranges > 0.0)):
        raise ValueError(f"state.sensor_ranges must all be finite and > 0 m; got {ranges}")
    if not 0.0 < azimuth_resolution_deg <= 10.0:
        raise ValueError(
            f"azimuth_resolution_deg must be in (0, 10] degrees; got {azimuth_resolution_deg}"
        )
    if not rsu_height_factor >= 0.0:
        raise ValueError(f"rsu_height_factor must be >= 0; got {rsu_height_factor}")
    if not 0.0 <= min_fraction < 1.0:
        raise ValueError(f"min_fraction must be in [0, 1); got {min_fraction}")


def _ray_pairs(corners: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Rays crossing each footprint: (candidate index (P,), unwrapped ray number k (P,))."""
    centre = corners.mean(axis=1)
    centre_angle = np.arctan2(centre[:, 1], centre[:, 0])
    rel = np.arctan2(corners[..., 1], corners[..., 0]) - centre_angle[:, None]
    rel = np.mod(rel + np.pi, 2.0 * np.pi) - np.pi
    k_lo = np.ceil((centre_angle + rel.min(axis=1)) / step).astype(np.int64)
    k_hi = np.floor((centre_angle + rel.max(axis=1)) / step).astype(np.int64)
    count = np.maximum(k_hi - k_lo + 1, 0)
    cand = np.repeat(np.arange(corners.shape[0]), count)
    first = np.repeat(np.cumsum(count) - count, count)
    return cand, k_lo[cand] + (np.arange(cand.size) - first)


def _slab_entry_exit(origin: np.ndarray, half: np.ndarray,
                     angle: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where rays enter and leave axis-aligned rectangles (slab method).

    origin (P, 2): ray origin in the rectangle's own frame (centred, axis
    aligned); half (P, 2): half length and half width; angle (P,): ray
    direction in that frame. Returns entry, exit distances (P,), entry clamped
    at 1 um; exit < entry means a miss (only grazing rays at a span edge).
    Columns are handled one by one: numpy reductions over a length-2 axis are slow.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        t_near, t_far = [], []
        for axis, direction in enumerate((np.cos(angle), np.sin(angle))):
            inv = 1.0 / direction  # +-inf for rays parallel to the slab
            t_a = (-half[:, axis] - origin[:, axis]) * inv
            t_b = (half[:, axis] - origin[:, axis]) * inv
            t_near.append(np.fmin(t_a, t_b))
            t_far.append(np.fmax(t_a, t_b))
    entry = np.maximum(np.fmax(t_near[0], t_near[1]), 1e-6)
    return entry, np.fmin(t_far[0], t_far[1])


def _shadow_slopes(key: np.ndarray, slope: np.ndarray) -> np.ndarray:
    """Max occluder slope strictly in front of each pair along its ray.

    key (P,) ray group, sorted ascending with pairs sorted by entry inside a
    group; slope (P,). Returns (P,), -inf where nothing is in front.
    """
    shifted = key * _GROUP_STRIDE + np.clip(slope, -_SLOPE_CLIP, _SLOPE_CLIP)
    running = np.maximum.accumulate(shifted) - key * _GROUP_STRIDE
    prev = np.full(key.shape, -np.inf)
    prev[1:] = running[:-1]
    group_start = np.ones(key.shape, dtype=bool)
    group_start[1:] = key[1:] != key[:-1]
    prev[group_start] = -np.inf
    return prev


def _candidates(poses: np.ndarray, ranges: np.ndarray, boxes: np.ndarray,
                not_self: np.ndarray, distance: np.ndarray, half_diag: np.ndarray,
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(agent, object) pairs worth casting, with the sensor origin in the box frame.

    Returns agent (C,), obj (C,), origin (C, 2) sensor position in the box's own
    frame, half (C, 2) half length/width. Boxes containing the sensor are dropped.
    """
    cand_a, cand_o = np.nonzero((distance <= ranges[:, None] + half_diag[None, :]) & not_self)
    offset = poses[cand_a, :2] - boxes[cand_o, :2]
    cb, sb = np.cos(boxes[cand_o, 6]), np.sin(boxes[cand_o, 6])
    origin = np.stack([cb * offset[:, 0] + sb * offset[:, 1],
                       -sb * offset[:, 0] + cb * offset[:, 1]], axis=1)
    half = 0.5 * boxes[cand_o, 3:5]
    keep = ~np.all(np.abs(origin) <= half, axis=1)
    return cand_a[keep], cand_o[keep], origin[keep], half[keep]


def _cast(poses: np.ndarray, boxes: np.ndarray, cand_a: np.ndarray, cand_o: np.ndarray,
          origin: np.ndarray, half: np.ndarray, step: float, n_rays: int,
          sort_stride: float) -> dict[str, np.ndarray]:
    """All (ray, object) crossings, sorted by ray group then entry distance.

    Returns arrays (P,): agent, obj, ray, angle (agent frame, rad), entry, exit
    (m) and key = agent * n_rays + ray.
    """
    ca, sa = np.cos(poses[cand_a, 2]), np.sin(poses[cand_a, 2])
    rel = box_corners_bev(boxes)[cand_o] - poses[cand_a, None, :2]
    corners = np.stack([ca[:, None] * rel[..., 0] + sa[:, None] * rel[..., 1],
                        -sa[:, None] * rel[..., 0] + ca[:, None] * rel[..., 1]], axis=-1)
    cand, k = _ray_pairs(corners, step)
    rel_yaw = boxes[cand_o, 6] - poses[cand_a, 2]
    entry, exit_ = _slab_entry_exit(origin[cand], half[cand], k * step - rel_yaw[cand])
    hit = np.flatnonzero(exit_ >= entry)
    ray = np.mod(k[hit], n_rays)
    key = cand_a[cand[hit]] * n_rays + ray
    pick = hit[np.argsort(key * sort_stride + entry[hit])]
    cand, k = cand[pick], k[pick]
    agent, ray = cand_a[cand], np.mod(k, n_rays)
    return {"agent": agent, "obj": cand_o[cand], "ray": ray, "angle": k * step,
            "entry": entry[pick], "exit": exit_[pick], "key": agent * n_rays + ray}


def _expected_returns(top: np.ndarray, low: np.ndarray, entry: np.ndarray,
                      h_sensor: np.ndarray, lidar: LidarModel, step: float) -> np.ndarray:
    """LiDAR points on each ray pair: beams inside the visible elevation interval.

    The visible part [low, top] (m above ground) at distance ``entry`` (m) seen
    from height ``h_sensor`` spans an elevation interval; clipped to the field
    of view and divided by the beam spacing it gives the beams hitting it, times
    the LiDAR azimuth steps per ray (``step`` rad).
    """
    el_hi = np.minimum(np.arctan2(top - h_sensor, entry), np.deg2rad(lidar.fov_up_deg))
    el_lo = np.maximum(np.arctan2(low - h_sensor, entry), np.deg2rad(lidar.fov_down_deg))
    beams = np.maximum(el_hi - el_lo, 0.0) / lidar.beam_spacing
    return beams * (step / np.deg2rad(lidar.horizontal_resolution_deg))


def compute_visibility(
    state: WorldState,
    azimuth_resolution_deg: float = 0.2,
    rsu_height_factor: float = 1.0,
    min_fraction: float = 0.05,
    lidar: LidarModel | None = None,
) -> Visibility:
    """Visibility of every object from every agent (model in the module docstring).

    azimuth_resolution_deg: ray spacing (degrees, rounded to tile 360);
    rsu_height_factor: RSU occlusion height / mast height (>= 0);
    min_fraction: visible-fraction threshold for ``visible``; lidar: beam model.
    Raises ValueError on non-positive sensor ranges or out-of-range arguments.
    """
    _check_inputs(state, azimuth_resolution_deg, rsu_height_factor, min_fraction)
    lidar = lidar or LidarModel()
    n_agents, n_obj = state.num_agents, state.num_objects
    n_rays = int(round(360.0 / azimuth_resolution_deg))
    step = 2.0 * np.pi / n_rays
    poses = np.asarray(state.agent_poses, dtype=float).reshape(n_agents, 3)
    ranges = np.asarray(state.sensor_ranges, dtype=float).reshape(n_agents)
    boxes = np.asarray(state.object_boxes, dtype=float).reshape(n_obj, 7)
    heights = np.asarray(state.sensor_heights, dtype=float).reshape(n_agents)
    is_rsu = np.array([kind == "rsu" for kind in state.agent_kinds], dtype=bool)
    occl_heights = np.where(is_rsu, heights * rsu_height_factor, heights)

    offset = boxes[None, :, :2] - poses[:, None, :2]
    distance = np.hypot(offset[..., 0], offset[..., 1])
    half_diag = 0.5 * np.hypot(boxes[:, 3], boxes[:, 4])
    not_self = state.object_ids[None, :] != np.asarray(state.agent_object_ids)[:, None]
    cand_a, cand_o, origin, half = _candidates(poses, ranges, boxes, not_self, distance, half_diag)
    stride = 4.0 * (ranges.max(initial=0.0) + half_diag.max(initial=0.0)) + 1.0
    pairs = _cast(poses, boxes, cand_a, cand_o, origin, half, step, n_rays, stride)
    agent, obj, entry = pairs["agent"], pairs["obj"], pairs["entry"]

    # 2.5D occlusion: the highest shadow cast by anything in front on the same ray.
    # Heights are measured from the ground under the agent (state.ground_heights).
    ground = np.asarray(state.ground_heights, dtype=float).reshape(n_agents)[agent]
    top = boxes[obj, 2] + 0.5 * boxes[obj, 5] - ground
    bottom = boxes[obj, 2] - 0.5 * boxes[obj, 5] - ground
    h_occ = occl_heights[agent]
    slope = np.maximum((top - h_occ) / entry, (top - h_occ) / pairs["exit"])
    low = np.maximum(bottom, h_occ + _shadow_slopes(pairs["key"], slope) * entry)
    vfrac = np.clip((top - low) / np.maximum(boxes[obj, 5], 1e-9), 0.0, 1.0)

    in_range = entry <= ranges[agent]
    returns = np.where(in_range & (vfrac > 0.0),
                       _expected_returns(top, low, entry, heights[agent], lidar, step), 0.0)

    flat, size = agent * n_obj + obj, n_agents * n_obj
    n_pairs = np.bincount(flat, minlength=size)
    fraction = np.bincount(flat, weights=np.where(in_range, vfrac, 0.0), minlength=size)
    fraction = np.divide(fraction, n_pairs, out=np.zeros(size), where=n_pairs > 0)
    centre_in_range = (distance <= ranges[:, None]) & not_self
    fraction = np.where(centre_in_range, fraction.reshape(n_agents, n_obj), 0.0)
    total_returns = np.bincount(flat, weights=returns, minlength=size).reshape(n_agents, n_obj)

    return Visibility(
        fraction=fraction,
        returns=np.where(centre_in_range, total_returns, 0.0),
        visible=centre_in_range & (fraction > min_fraction),
        distance=distance,
        azimuth_step=step,
        _pairs=_RayPairs(agent, obj, pairs["ray"], pairs["angle"], entry, top, returns, ranges,
                         n_rays),
    )
