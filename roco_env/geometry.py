"""SE(2) poses, 3D boxes, exact rotated-rectangle IoU in BEV and rotated NMS.

Conventions (docs/conventions.md): right-handed frames, x forward, y left, z up;
yaw in radians, counter-clockwise from +x, wrapped to (-pi, pi]. A pose is
``(x, y, yaw)``; a box is ``(x, y, z, l, w, h, yaw)`` with its centre and full
sizes in metres. ``T_{j->i} = E_i^{-1} E_j`` maps points of frame j into frame i.

Everything is vectorised over leading batch dimensions.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "wrap_angle",
    "AXIAL_HEADING_LOW",
    "canonical_axial_yaw",
    "se2_to_matrix",
    "matrix_to_se2",
    "se2_compose",
    "apply_correction",
    "se2_inverse",
    "se2_relative",
    "se2_apply",
    "transform_boxes",
    "box_corners_bev",
    "validate_boxes",
    "bev_iou",
    "bev_iou_pairs",
    "bev_candidate_pairs",
    "nms_bev",
]


def wrap_angle(angle: np.ndarray | float) -> np.ndarray:
    """Wrap angles (radians) to the half-open interval (-pi, pi]."""
    wrapped = np.mod(np.asarray(angle, dtype=float) + np.pi, 2.0 * np.pi) - np.pi
    return np.where(wrapped <= -np.pi, wrapped + 2.0 * np.pi, wrapped)


# Axial headings (known up to pi) are reported in this half-turn [lo, lo + pi) of the
# receiving frame: its edges lie on the diagonals, away from the 0 and +-pi/2 headings
# of traffic on axis-aligned roads, so pose noise of a few degrees rarely moves a
# heading across an edge.
AXIAL_HEADING_LOW = -np.pi / 4


def canonical_axial_yaw(yaw: np.ndarray, frame_yaw: np.ndarray | float = 0.0) -> np.ndarray:
    """Axial headings (rad, known up to pi) moved by a multiple of pi so that, seen from a
    frame rotated by ``frame_yaw`` relative to theirs (heading + frame_yaw), they lie in
    [AXIAL_HEADING_LOW, AXIAL_HEADING_LOW + pi); returned in their own frame, wrapped
    to (-pi, pi]. Two agents that report the same object this way agree on its heading
    whenever their frames are known to within the distance to the half-turn's edges."""
    seen = np.asarray(yaw, dtype=float) + frame_yaw
    shifted = AXIAL_HEADING_LOW + np.mod(seen - AXIAL_HEADING_LOW, np.pi)
    return wrap_angle(np.asarray(yaw, dtype=float) + (shifted - seen))


def _as_poses(poses: np.ndarray, name: str) -> np.ndarray:
    poses = np.asarray(poses, dtype=float)
    if poses.shape[-1:] != (3,):
        raise ValueError(f"{name} must have shape (..., 3) = (x, y, yaw); got {poses.shape}")
    return poses


def se2_to_matrix(poses: np.ndarray) -> np.ndarray:
    """Poses (..., 3) -> homogeneous matrices (..., 3, 3)."""
    poses = _as_poses(poses, "poses")
    c, s = np.cos(poses[..., 2]), np.sin(poses[..., 2])
    mats = np.zeros(poses.shape[:-1] + (3, 3))
    mats[..., 0, 0], mats[..., 0, 1], mats[..., 0, 2] = c, -s, poses[..., 0]
    mats[..., 1, 0], mats[..., 1, 1], mats[..., 1, 2] = s, c, poses[..., 1]
    mats[..., 2, 2] = 1.0
    return mats


def matrix_to_se2(mats: np.ndarray) -> np.ndarray:
    """Homogeneous matrices (..., 3, 3) -> poses (..., 3), yaw wrapped."""
    mats = np.asarray(mats, dtype=float)
    if mats.shape[-2:] != (3, 3):
        raise ValueError(f"mats must have shape (..., 3, 3); got {mats.shape}")
    yaw = np.arctan2(mats[..., 1, 0], mats[..., 0, 0])
    return np.stack([mats[..., 0, 2], mats[..., 1, 2], wrap_angle(yaw)], axis=-1)


def se2_compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Composition ``a * b`` (apply b first, then a); broadcasts over batches."""
    a, b = _as_poses(a, "a"), _as_poses(b, "b")
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    return np.stack([x, y, wrap_angle(a[..., 2] + b[..., 2])], axis=-1)


def apply_correction(reported: np.ndarray, action: np.ndarray) -> np.ndarray:
    """The env's action rule: ``T_corrected = SE2(action) * T_reported``, per slot (N, 3).

    Lives here, below both the env and the policies, so neither imports the other.
    """
    return se2_compose(np.asarray(action, dtype=float), np.asarray(reported, dtype=float))


def se2_inverse(a: np.ndarray) -> np.ndarray:
    """Inverse pose ``a^{-1}``."""
    a = _as_poses(a, "a")
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = -(c * a[..., 0] + s * a[..., 1])
    y = -(-s * a[..., 0] + c * a[..., 1])
    return np.stack([x, y, wrap_angle(-a[..., 2])], axis=-1)


def se2_relative(pose_i: np.ndarray, pose_j: np.ndarray) -> np.ndarray:
    """Relative pose ``T_{j->i} = E_i^{-1} E_j`` (maps j-frame points into frame i)."""
    return se2_compose(se2_inverse(pose_i), pose_j)


def se2_apply(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply pose(s) (..., 3) to 2D points (..., 2); shapes broadcast."""
    pose = _as_poses(pose, "pose")
    points = np.asarray(points, dtype=float)
    c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    x = pose[..., 0] + c * points[..., 0] - s * points[..., 1]
    y = pose[..., 1] + s * points[..., 0] + c * points[..., 1]
    return np.stack([x, y], axis=-1)


def validate_boxes(boxes: np.ndarray, name: str = "boxes") -> np.ndarray:
    """Return ``boxes`` as a float (N, 7) array or raise ValueError naming ``name``.

    Rejects wrong shapes, NaN/inf values and negative sizes (l, w, h).
    """
    arr = np.asarray(boxes, dtype=float)
    if arr.ndim == 1 and arr.size == 0:
        arr = arr.reshape(0, 7)
    if arr.ndim != 2 or arr.shape[1] != 7:
        raise ValueError(
            f"{name} must have shape (N, 7) = (x, y, z, l, w, h, yaw); got {arr.shape}"
        )
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} contains NaN or inf; all values must be finite")
    if (arr[:, 3:6] < 0).any():
        raise ValueError(f"{name} has negative sizes; l, w, h (columns 3-5) must be >= 0")
    return arr


def transform_boxes(boxes: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Map boxes (N, 7) from frame A into frame B, where ``pose`` = T_{A->B} (3,).

    Centres are rotated and translated, yaw gets the pose's rotation added
    (wrapped); z and sizes are unchanged.
    """
    boxes = np.asarray(boxes, dtype=float).reshape(-1, 7)
    pose = _as_poses(pose, "pose")
    out = boxes.copy()
    out[:, :2] = se2_apply(pose, boxes[:, :2])
    out[:, 6] = wrap_angle(boxes[:, 6] + pose[..., 2])
    return out


# Unit-square corners in counter-clockwise order (front-left last).
_CORNER_SIGNS = np.array([[0.5, 0.5], [-0.5, 0.5], [-0.5, -0.5], [0.5, -0.5]])
# Corner signs of the half length / half width going round the footprint
# counter-clockwise and back to the first corner, shaped (5, 1) to broadcast.
_LOOP_LENGTH = np.array([1.0, -1.0, -1.0, 1.0, 1.0])[:, None]
_LOOP_WIDTH = np.array([1.0, 1.0, -1.0, -1.0, 1.0])[:, None]


def box_corners_bev(boxes: np.ndarray) -> np.ndarray:
    """BEV footprint corners (N, 4, 2) of boxes (N, 7), counter-clockwise."""
    boxes = np.asarray(boxes, dtype=float).reshape(-1, 7)
    local = _CORNER_SIGNS[None, :, :] * boxes[:, None, 3:5]
    c, s = np.cos(boxes[:, 6])[:, None], np.sin(boxes[:, 6])[:, None]
    x = boxes[:, None, 0] + c * local[..., 0] - s * local[..., 1]
    y = boxes[:, None, 1] + s * local[..., 0] + c * local[..., 1]
    return np.stack([x, y], axis=-1)


# Pairs per vectorised block: the (4, 4, block) temporaries then stay in the CPU
# cache, faster than one block of 40,000 pairs (docs/performance.md).
_BLOCK = 4096


def _rectangle_intersection_area(boxes_a: np.ndarray, boxes_b: np.ndarray) -> np.ndarray:
    """Exact area of the intersection of the BEV rectangles of aligned pairs (P,)."""
    if boxes_a.shape[0] <= _BLOCK:
        return _block_intersection_area(boxes_a, boxes_b)
    return np.concatenate([
        _block_intersection_area(boxes_a[start:start + _BLOCK], boxes_b[start:start + _BLOCK])
        for start in range(0, boxes_a.shape[0], _BLOCK)
    ])


def _block_intersection_area(boxes_a: np.ndarray, boxes_b: np.ndarray) -> np.ndarray:
    """Intersection areas (P,) of rectangle pairs, by Green's theorem in B's own frame.

    Written by hand because no installed library does this vectorised (shapely
    is exact but works one pair at a time). In B's frame B is the axis-aligned
    rectangle [-hx, hx] x [-hy, hy] around the origin, and the intersection's
    counter-clockwise boundary is (edges of A inside B) + (sides of B inside A):

        area = sum over A's edges of cross(start, end) / 2 of the part inside B
             + sum over B's sides k of h_k * (length of side k inside A) / 2,

    with h_k the distance of side k from the origin. Each crossing of an A edge
    with a side line is computed once and used for both pieces, so the boundary
    closes even for (nearly) coincident edges; a corner exactly on a side line
    counts as inside B, so a shared edge is counted once. Only A's pose relative
    to B enters, so precision does not depend on the distance to the world origin.
    """
    # Layout (..., P): reductions over sides/corners are element-wise on contiguous
    # rows. Written with few numpy calls: per-frame metrics call this on a handful of pairs.
    n_pairs = boxes_a.shape[0]
    a, b = np.ascontiguousarray(boxes_a.T), np.ascontiguousarray(boxes_b.T)
    cos_b, sin_b = np.cos(b[6]), np.sin(b[6])
    rel_yaw = a[6] - b[6]
    cos_r, sin_r = np.cos(rel_yaw), np.sin(rel_yaw)
    dx, dy = a[0] - b[0], a[1] - b[1]
    half_l, half_w = 0.5 * a[3], 0.5 * a[4]
    # A's corners in B's frame (2, 5, P), counter-clockwise as in box_corners_bev, the
    # first repeated at the end so that edge k runs from corner k to corner k + 1.
    xy = np.empty((2, 5, n_pairs))
    xy[0] = (cos_b * dx + sin_b * dy) + _LOOP_LENGTH * (half_l * cos_r) - _LOOP_WIDTH * (
        half_w * sin_r
    )
    xy[1] = (cos_b * dy - sin_b * dx) + _LOOP_LENGTH * (half_l * sin_r) + _LOOP_WIDTH * (
        half_w * cos_r
    )
    start_xy, edge = xy[:, :4], xy[:, 1:] - xy[:, :4]  # (2, 4 edges, P)
    hx, hy = 0.5 * b[3], 0.5 * b[4]
    # Inside-distance of A's corners to B's side lines, sides counter-clockwise:
    # right (x = hx), top (y = hy), left (x = -hx), bottom (y = -hy). (4 sides, 5, P)
    dist = np.empty((4, 5, n_pairs))
    np.subtract(hx, xy[0], out=dist[0])
    np.subtract(hy, xy[1], out=dist[1])
    np.add(hx, xy[0], out=dist[2])
    np.add(hy, xy[1], out=dist[3])
    inside_line = dist >= 0.0
    s0, s1 = dist[:, :4], dist[:, 1:]  # at the start / end corner of each A edge
    in0, in1 = inside_line[:, :4], inside_line[:, 1:]
    crossing = in0 != in1
    # Crossing coordinate along each side's line (y on right/left, x on top/bottom).
    along = np.empty((4, 4, n_pairs))
    with np.errstate(divide="ignore", invalid="ignore"):
        t = s0 / (s0 - s1)  # edge parameter of the crossing, read only where crossing
        np.add(start_xy[1], t[0::2] * edge[1], out=along[0::2])
        np.add(start_xy[0], t[1::2] * edge[0], out=along[1::2])
    # Part of each A edge inside B: parameter interval [t_lo, t_hi] (4 edges, P); a
    # side with both ends outside closes it (t_hi = 0).
    t_lo = np.where(crossing & in1, t, 0.0).max(axis=0)
    t_hi = np.where(crossing & in0, t, in1).min(axis=0)
    # cross(p + t_lo e, p + t_hi e) = (t_hi - t_lo) cross(p, e) for edge start p, vector e.
    moment = start_xy[0] * edge[1] - start_xy[1] * edge[0]
    area_a_edges = (moment * np.maximum(t_hi - t_lo, 0.0)).sum(axis=0)
    # Part of each B side inside A: between the crossings of A's boundary with its line;
    # right/left sides have half length hy and distance hx from the centre, top/bottom hx, hy.
    low = np.where(crossing, along, np.inf).min(axis=1)
    high = np.where(crossing, along, -np.inf).max(axis=1)
    length_rl = np.minimum(high[0::2], hy) - np.maximum(low[0::2], -hy)
    length_tb = np.minimum(high[1::2], hx) - np.maximum(low[1::2], -hx)
    area_b_sides = (hx * np.maximum(length_rl, 0.0).sum(axis=0)
                    + hy * np.maximum(length_tb, 0.0).sum(axis=0))
    return 0.5 * (area_a_edges + area_b_sides)


def bev_iou_pairs(boxes_a: np.ndarray, boxes_b: np.ndarray) -> np.ndarray:
    """IoU of BEV footprints for aligned pairs: boxes_a[k] vs boxes_b[k] -> (P,)."""
    boxes_a = validate_boxes(boxes_a, "boxes_a")
    boxes_b = validate_boxes(boxes_b, "boxes_b")
    if boxes_a.shape != boxes_b.shape:
        raise ValueError(
            f"boxes_a and boxes_b must have the same shape; got {boxes_a.shape} and {boxes_b.shape}"
        )
    return _pair_iou(boxes_a, boxes_b)


def _pair_iou(boxes_a: np.ndarray, boxes_b: np.ndarray) -> np.ndarray:
    area_a = boxes_a[:, 3] * boxes_a[:, 4]
    area_b = boxes_b[:, 3] * boxes_b[:, 4]
    # Clamp rounding so that 0 <= inter <= min(area), hence 0 <= IoU <= 1; the
    # union is then >= max(area) and zero only when both boxes have zero area.
    inter = np.clip(_rectangle_intersection_area(boxes_a, boxes_b), 0.0,
                    np.minimum(area_a, area_b))
    union = area_a + area_b - inter
    return inter / np.where(union > 0.0, union, 1.0)


def bev_iou(boxes_a: np.ndarray, boxes_b: np.ndarray) -> np.ndarray:
    """Exact IoU (N, M) between the BEV footprints of boxes_a (N, 7) and boxes_b (M, 7).

    Pairs whose circumscribed circles do not overlap are skipped (IoU 0), so
    sparse scenes cost little more than the distance test.
    """
    boxes_a = validate_boxes(boxes_a, "boxes_a")
    boxes_b = validate_boxes(boxes_b, "boxes_b")
    iou = np.zeros((boxes_a.shape[0], boxes_b.shape[0]))
    ia, ib = _candidate_pairs(boxes_a, boxes_b)
    if ia.size:
        iou[ia, ib] = _pair_iou(boxes_a[ia], boxes_b[ib])
    return iou


def bev_candidate_pairs(
    boxes_a: np.ndarray,
    boxes_b: np.ndarray,
    groups_a: np.ndarray | None = None,
    groups_b: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (ia, ib) whose BEV footprints may overlap, sorted by ia then ib.

    A superset of the pairs with IoU > 0: the boxes' circumscribed circles
    overlap (strictly). boxes_a (N, 7), boxes_b (M, 7). With ``groups_a`` (N,)
    and ``groups_b`` (M,), integer labels sorted ascending (e.g. frame numbers),
    only pairs within the same group are considered, all groups in one pass.
    """
    boxes_a = validate_boxes(boxes_a, "boxes_a")
    boxes_b = validate_boxes(boxes_b, "boxes_b")
    if groups_a is None and groups_b is None:
        return _candidate_pairs(boxes_a, boxes_b)
    groups_a = _sorted_groups(groups_a, boxes_a.shape[0], "groups_a")
    groups_b = _sorted_groups(groups_b, boxes_b.shape[0], "groups_b")
    # All (a, b) pairs of equal group: b runs over [first, last) of a's group.
    first = np.searchsorted(groups_b, groups_a, side="left")
    count = np.searchsorted(groups_b, groups_a, side="right") - first
    ia = np.repeat(np.arange(boxes_a.shape[0]), count)
    ib = np.arange(ia.size) - np.repeat(np.cumsum(count) - count - first, count)
    a, b = boxes_a[ia], boxes_b[ib]
    reach = 0.5 * (np.hypot(a[:, 3], a[:, 4]) + np.hypot(b[:, 3], b[:, 4]))
    near = np.square(a[:, 0] - b[:, 0]) + np.square(a[:, 1] - b[:, 1]) < np.square(reach)
    return ia[near], ib[near]


def _sorted_groups(groups: np.ndarray | None, n: int, name: str) -> np.ndarray:
    if groups is None:
        raise ValueError("groups_a and groups_b must be given together")
    arr = np.asarray(groups)
    if arr.shape != (n,) or not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"{name} must be ({n},) integer group labels; got {arr.dtype} {arr.shape}")
    if n > 1 and (np.diff(arr) < 0).any():
        raise ValueError(f"{name} must be sorted ascending")
    return arr


def _candidate_pairs(boxes_a: np.ndarray, boxes_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    radius_a = 0.5 * np.hypot(boxes_a[:, 3], boxes_a[:, 4])
    radius_b = 0.5 * np.hypot(boxes_b[:, 3], boxes_b[:, 4])
    gap = np.square(boxes_a[:, None, 0] - boxes_b[None, :, 0])
    gap += np.square(boxes_a[:, None, 1] - boxes_b[None, :, 1])
    return np.nonzero(gap < np.square(radius_a[:, None] + radius_b[None, :]))


def nms_bev(boxes: np.ndarray, scores: np.ndarray, iou_threshold: float) -> np.ndarray:
    """Rotated non-maximum suppression in BEV.

    Visits boxes by descending score (ties keep input order) and drops every
    box whose IoU with an already kept box exceeds ``iou_threshold``.
    Returns the kept indices, highest score first.
    """
    boxes = validate_boxes(boxes, "boxes")
    scores = np.asarray(scores, dtype=float).reshape(-1)
    if scores.shape[0] != boxes.shape[0]:
        raise ValueError(
            f"scores must have one entry per box ({boxes.shape[0]}); got {scores.shape[0]}"
        )
    if not np.all(np.isfinite(scores)):
        raise ValueError("scores contains NaN or inf; all values must be finite")
    if not 0.0 <= iou_threshold <= 1.0:
        raise ValueError(f"iou_threshold must be in [0, 1]; got {iou_threshold}")
    order = np.argsort(-scores, kind="stable")
    iou = bev_iou(boxes[order], boxes[order])
    suppressed = np.zeros(order.size, dtype=bool)
    kept = []
    for rank in range(order.size):
        if suppressed[rank]:
            continue
        kept.append(order[rank])
        suppressed |= iou[rank] > iou_threshold
    return np.asarray(kept, dtype=np.int64)
