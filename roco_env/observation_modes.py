"""What an agent observes: the modes of the scenario section ``observation``.

* ``raw`` (default): the contract's Dict of :mod:`roco_env.observation` (each
  collaborator's boxes in its own frame, world poses as reported).
* ``aligned``: everything already in the ego's frame, for MLP policies. The own boxes;
  each collaborator's boxes moved into the ego frame through the pose the action acts on
  (the base aligner's in ``residual`` and ``gate`` action modes, the reported one
  otherwise), that pose, the reported one (``collab_reported_poses``, what the messages
  say: the raw mode's ``collab_rel_poses``), and per slot the base aligner's diagnostics
  (:data:`DIAGNOSTICS`). The base aligner is ``action.base`` and runs on every
  observation in this mode. In ``select`` action mode it also holds
  ``choice_diagnostics`` (N, C, len(:data:`CHOICE_DIAGNOSTICS`)): per slot, each of the
  C ``action.choices``' diagnostics and how far its pose lies from the others' (two
  independent aligners that agree are rarely both wrong); every choice then runs on
  every observation, and the action reuses their poses.
* ``bev``: occupancy rasters for CNN policies: ``bev`` uint8 (N + 1, H, W), channel 0 the
  ego's own boxes, channel 1 + j collaborator slot j's boxes moved into the ego frame as
  in ``aligned`` (cells inside a box 255, else 0; so channel 0 with channel 1 + j is
  slot j's ego / collaborator pair), and ``collab_mask``. Row r, column c is the cell
  centred at x = R - (r + 1/2) s, y = R - (c + 1/2) s in the ego frame (R =
  ``observation.bev_range``, s = ``observation.bev_resolution``): forward is up, left is
  left.

Spaces of the new modes have finite bounds; values are clipped into them (boxes and poses
to +-:data:`EGO_FRAME_BOUND` m, diagnostics to their columns' bounds).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
from gymnasium import spaces

from roco_env.geometry import se2_compose, se2_inverse, transform_boxes
from roco_env.observation import EgoView
from roco_env.scenario import ObservationConfig

if TYPE_CHECKING:
    from roco_env.policies.base import AlignmentResult

_F32 = np.float32
EGO_FRAME_BOUND = 2000.0  # m: beyond any communication plus sensor range
MAX_AGE_MS = 60000.0  # ms: the largest comm.max_age_ms a scenario accepts
# Per-slot diagnostics of the base aligner (aligned mode), with their bounds.
DIAGNOSTICS: tuple[tuple[str, float, float, str], ...] = (
    ("applied", 0.0, 1.0, "1 where the aligner corrected the reported pose"),
    ("pairs", 0.0, 1024.0, "boxes it matched between the ego and this collaborator"),
    ("residual_m", 0.0, 100.0, "mean centre distance of those pairs after its pose, m "
     "(0 without pairs)"),
    ("statistic", -1.0, 1000.0, "its do-no-harm test statistic (chi-square, 3 dof); -1 "
     "where it computed none"),
    ("shift_m", 0.0, 100.0, "translation between its pose and the reported one, m"),
    ("turn_deg", 0.0, 180.0, "rotation between its pose and the reported one, degrees"),
    ("distance_m", 0.0, 1000.0, "distance to the collaborator as reported, m"),
    ("boxes", 0.0, 1024.0, "boxes the collaborator sent"),
    ("age_ms", 0.0, MAX_AGE_MS, "age of the collaborator's scan the ego holds, ms (0 "
     "without the network stage: every message is of now)"),
)
_DIAG_LOW = np.array([d[1] for d in DIAGNOSTICS], dtype=_F32)
_DIAG_HIGH = np.array([d[2] for d in DIAGNOSTICS], dtype=_F32)
_OWN = 6  # the first columns of DIAGNOSTICS describe the aligner's call; the rest the slot
AGREE_M, AGREE_DEG = 1.0, 1.0  # two poses agree within this translation (m) and rotation
_MOVED = 1e-9  # m, rad: a pose change below this is float rounding (an identity's), not applied
# Per slot and choice (select mode): the choice's own columns of DIAGNOSTICS, then how it
# sits among the other choices; bounds tighter than DIAGNOSTICS' (beyond them all is "far").
CHOICE_DIAGNOSTICS: tuple[tuple[str, float, float, str], ...] = (
    ("applied", 0.0, 1.0, "1 where the choice corrected the reported pose"),
    ("pairs", 0.0, 64.0, "boxes it matched between the ego and this collaborator"),
    ("residual_m", 0.0, 10.0, "mean centre distance of those pairs after its pose, m"),
    ("statistic", -1.0, 100.0, "its do-no-harm statistic; -1 where it computed none"),
    ("shift_m", 0.0, 20.0, "translation between its pose and the reported one, m"),
    ("turn_deg", 0.0, 20.0, "rotation between its pose and the reported one, degrees"),
    ("agreeing", 0.0, 8.0, f"other choices whose pose lies within {AGREE_M:g} m and "
     f"{AGREE_DEG:g} deg of this one's"),
    ("gap_m", 0.0, 20.0, "translation between its pose and the nearest other choice's, m"),
)
_CHOICE_LOW = np.array([d[1] for d in CHOICE_DIAGNOSTICS], dtype=_F32)
_CHOICE_HIGH = np.array([d[2] for d in CHOICE_DIAGNOSTICS], dtype=_F32)


def bev_shape(config: ObservationConfig) -> tuple[int, int]:
    """(H, W) cells of the bev raster."""
    side = int(round(2.0 * config.bev_range / config.bev_resolution))
    return side, side


def mode_space(config: ObservationConfig, max_boxes: int, max_collaborators: int,
               choices: int = 0) -> spaces.Dict:
    """The Dict space of the ``aligned`` or ``bev`` mode; ``choices``: the number of
    select-mode choices (0: no ``choice_diagnostics``)."""
    k, n = max_boxes, max_collaborators
    if config.mode == "bev":
        return spaces.Dict({
            "bev": spaces.Box(0, 255, (n + 1, *bev_shape(config)), np.uint8),
            "collab_mask": spaces.Box(0, 1, (n,), np.int8),
        })
    boxes = _box_bounds(k)
    per_choice = {} if not choices else {"choice_diagnostics": spaces.Box(
        np.tile(_CHOICE_LOW, (n, choices, 1)), np.tile(_CHOICE_HIGH, (n, choices, 1)),
        dtype=_F32)}
    return spaces.Dict({
        "boxes": spaces.Box(-boxes, boxes, dtype=_F32),
        "scores": spaces.Box(0.0, 1.0, (k,), _F32),
        "box_mask": spaces.Box(0, 1, (k,), np.int8),
        "collab_mask": spaces.Box(0, 1, (n,), np.int8),
        "collab_rel_poses": spaces.Box(-_pose_bounds(n), _pose_bounds(n), dtype=_F32),
        "collab_reported_poses": spaces.Box(-_pose_bounds(n), _pose_bounds(n), dtype=_F32),
        "collab_boxes": spaces.Box(-np.tile(boxes, (n, 1, 1)), np.tile(boxes, (n, 1, 1)),
                                   dtype=_F32),
        "collab_scores": spaces.Box(0.0, 1.0, (n, k), _F32),
        "collab_box_mask": spaces.Box(0, 1, (n, k), np.int8),
        "diagnostics": spaces.Box(np.tile(_DIAG_LOW, (n, 1)), np.tile(_DIAG_HIGH, (n, 1)),
                                  dtype=_F32),
        **per_choice,
    })


def build_observation(config: ObservationConfig, view: EgoView, raw: dict,
                      poses: np.ndarray, base: AlignmentResult | None,
                      base_poses: np.ndarray | None,
                      choices: Sequence[tuple[AlignmentResult | None, np.ndarray]] = (),
                      ) -> dict[str, np.ndarray]:
    """The ``aligned`` or ``bev`` observation of ``view``.

    raw: its packed raw observation (the boxes the agent keeps, padded); poses: (n, 3) the
    relative poses ``T_{j->i}`` that move each filled slot's boxes into the ego frame;
    base / base_poses: the base aligner's result and (n, 3) poses (aligned mode);
    choices: each select-mode choice's (result, (n, 3) poses), in order (aligned mode;
    empty: no ``choice_diagnostics``).
    """
    n = len(view.collaborators)
    moved = np.zeros_like(raw["collab_boxes"])
    for slot in range(n):
        count = int(raw["collab_box_mask"][slot].sum())
        moved[slot, :count] = transform_boxes(raw["collab_boxes"][slot, :count], poses[slot])
    if config.mode == "bev":
        return {"bev": _rasters(raw["boxes"][raw["box_mask"] > 0], moved, raw["collab_box_mask"],
                                config),
                "collab_mask": raw["collab_mask"].copy()}
    bounds = _box_bounds(raw["boxes"].shape[0])
    rel = np.zeros_like(raw["collab_rel_poses"])
    rel[:n] = poses
    pose_bound = _pose_bounds(1)[0]
    return {
        "boxes": np.clip(raw["boxes"], -bounds, bounds).astype(_F32),
        "scores": raw["scores"].copy(),
        "box_mask": raw["box_mask"].copy(),
        "collab_mask": raw["collab_mask"].copy(),
        "collab_rel_poses": np.clip(rel, -pose_bound, pose_bound).astype(_F32),
        "collab_reported_poses": np.clip(raw["collab_rel_poses"], -pose_bound,
                                         pose_bound).astype(_F32),
        "collab_boxes": np.clip(moved, -bounds, bounds).astype(_F32),
        "collab_scores": raw["collab_scores"].copy(),
        "collab_box_mask": raw["collab_box_mask"].copy(),
        "diagnostics": diagnostics(view, raw, base, base_poses),
        **({"choice_diagnostics": choice_diagnostics(view, raw, choices)} if choices else {}),
    }


def diagnostics(view: EgoView, raw: dict, base: AlignmentResult | None,
                base_poses: np.ndarray) -> np.ndarray:
    """(N, len(DIAGNOSTICS)) float32 per-slot diagnostics of the base aligner (zeros for
    empty slots), clipped to their bounds."""
    n_slots = raw["collab_mask"].shape[0]
    rows = np.zeros((n_slots, len(DIAGNOSTICS)), dtype=float)
    rows[:, 3] = -1.0
    for slot in range(len(view.collaborators)):
        change = se2_compose(base_poses[slot], se2_inverse(view.reported_relative[slot]))
        pairs = _ego_pairs(base, slot)
        rows[slot] = (
            bool(base.applied[slot]) if base is not None
            else bool(np.any(np.abs(change) > _MOVED)),
            pairs.shape[0],
            _pair_residual(raw, slot, pairs, base_poses[slot]),
            _statistic(base, slot),
            np.hypot(change[0], change[1]),
            abs(np.degrees(change[2])),
            np.hypot(*view.reported_relative[slot, :2]),
            view.collab_scores[slot].shape[0],
            0.0 if view.collab_age is None else 1000.0 * float(view.collab_age[slot]),
        )
    return np.clip(rows, _DIAG_LOW, _DIAG_HIGH).astype(_F32)


def choice_diagnostics(view: EgoView, raw: dict,
                       choices: Sequence[tuple[AlignmentResult | None, np.ndarray]]
                       ) -> np.ndarray:
    """(N, C, len(CHOICE_DIAGNOSTICS)) float32: per slot, each choice's own diagnostics
    and its agreement with the other choices' poses (zeros for empty slots, statistic -1),
    clipped to their bounds."""
    n_slots, n = raw["collab_mask"].shape[0], len(view.collaborators)
    rows = np.zeros((n_slots, len(choices), len(CHOICE_DIAGNOSTICS)), dtype=float)
    rows[:, :, 3] = -1.0
    for index, (result, poses) in enumerate(choices):
        rows[:, index, :_OWN] = diagnostics(view, raw, result, poses)[:, :_OWN]
    if n and len(choices) > 1:
        stacked = np.stack([np.asarray(poses, dtype=float)[:n] for _, poses in choices],
                           axis=1)  # (n, C, 3)
        apart = stacked[:, :, None, :] - stacked[:, None, :, :]  # (n, C, C, 3)
        metres = np.hypot(apart[..., 0], apart[..., 1])
        degrees = np.degrees(np.abs(np.angle(np.exp(1j * apart[..., 2]))))
        others = ~np.eye(len(choices), dtype=bool)
        rows[:n, :, 6] = ((metres <= AGREE_M) & (degrees <= AGREE_DEG) & others).sum(axis=2)
        rows[:n, :, 7] = np.where(others, metres, np.inf).min(axis=2)
    return np.clip(rows, _CHOICE_LOW, _CHOICE_HIGH).astype(_F32)


def _ego_pairs(base: AlignmentResult | None, slot: int) -> np.ndarray:
    """(P, 2) (ego box, collaborator box) indices the aligner matched for ``slot``."""
    if base is None or base.matched_pairs.shape[0] == 0:
        return np.zeros((0, 2), dtype=np.int64)
    rows = base.matched_pairs
    forward = rows[(rows[:, 0] == -1) & (rows[:, 2] == slot)][:, [1, 3]]
    backward = rows[(rows[:, 2] == -1) & (rows[:, 0] == slot)][:, [3, 1]]
    return np.concatenate([forward, backward])


def _pair_residual(raw: dict, slot: int, pairs: np.ndarray, pose: np.ndarray) -> float:
    """Mean ego-frame centre distance (m) of the matched pairs under ``pose``; 0 without."""
    if pairs.shape[0] == 0:
        return 0.0
    theirs = transform_boxes(raw["collab_boxes"][slot, pairs[:, 1]], pose)
    mine = raw["boxes"][pairs[:, 0]]
    return float(np.mean(np.hypot(*(theirs[:, :2] - mine[:, :2]).T)))


def _statistic(base: AlignmentResult | None, slot: int) -> float:
    """The aligner's significance statistic for ``slot``, -1 where it computed none."""
    if base is None or slot >= len(base.slot_statistics):
        return -1.0
    value = base.slot_statistics[slot]
    return float(value) if np.isfinite(value) else -1.0


def _rasters(own: np.ndarray, moved: np.ndarray, collab_mask: np.ndarray,
             config: ObservationConfig) -> np.ndarray:
    """(N + 1, H, W) uint8 occupancy: own boxes, then each slot's moved boxes."""
    h, w = bev_shape(config)
    half, cell = config.bev_range, config.bev_resolution
    xs = half - (np.arange(h) + 0.5) * cell  # row centres along x, forward first
    ys = half - (np.arange(w) + 0.5) * cell  # column centres along y, left first
    out = np.zeros((moved.shape[0] + 1, h, w), dtype=np.uint8)
    out[0] = _occupancy(own, xs, ys)
    for slot in range(moved.shape[0]):
        out[slot + 1] = _occupancy(moved[slot][collab_mask[slot] > 0], xs, ys)
    return out


def _occupancy(boxes: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """255 where a cell centre lies inside a box footprint, else 0 (H, W) uint8.

    Point-in-rotated-rectangle on each box's axis-aligned window of cells: the raster
    is small and numpy does it in a few vectorised steps, so no polygon library is needed.
    """
    grid = np.zeros((xs.shape[0], ys.shape[0]), dtype=np.uint8)
    step = abs(xs[0] - xs[1]) if xs.shape[0] > 1 else 1.0
    for x, y, _, length, width, _, yaw in np.asarray(boxes, dtype=float):
        reach = 0.5 * np.hypot(length, width)
        rows = np.flatnonzero(np.abs(xs - x) <= reach + step)
        cols = np.flatnonzero(np.abs(ys - y) <= reach + step)
        if rows.size == 0 or cols.size == 0:
            continue
        dx = xs[rows][:, None] - x
        dy = ys[cols][None, :] - y
        c, s = np.cos(yaw), np.sin(yaw)
        inside = (np.abs(c * dx + s * dy) <= 0.5 * length) & \
            (np.abs(-s * dx + c * dy) <= 0.5 * width)
        grid[np.ix_(rows, cols)] |= np.where(inside, 255, 0).astype(np.uint8)
    return grid


def _box_bounds(k: int) -> np.ndarray:
    """(k, 7) bounds of boxes in the ego frame (centre and sizes in m, yaw in rad)."""
    row = np.array([EGO_FRAME_BOUND] * 6 + [np.pi], dtype=_F32)
    return np.tile(row, (k, 1))


def _pose_bounds(n: int) -> np.ndarray:
    """(n, 3) bounds of relative poses (x m, y m, yaw rad)."""
    return np.tile(np.array([EGO_FRAME_BOUND, EGO_FRAME_BOUND, np.pi], dtype=_F32), (n, 1))
