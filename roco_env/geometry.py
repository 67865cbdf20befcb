"""SE(2) poses, 3D boxes, exact rotated-rectangle IoU in BEV and rotated NMS.

Conventions (DESIGN.md section 3): right-handed frames, x forward, y left, z up;
yaw in radians, counter-clockwise from +x, wrapped to (-pi, pi]. A pose is
``(x, y, yaw)``; a box is ``(x, y, z, l, w, h, yaw)`` with its centre and full
sizes in metres. ``T_{j->i} = E_i^{-1} E_j`` maps points of frame j into frame i.

Everything is vectorised over leading batch dimensions.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "wrap_angle",
    "se2_to_matrix",
    "matrix_to_se2",
    "se2_compose",
    "se2_inverse",
    "se2_relative",
    "se2_apply",
    "transform_boxes",
    "box_corners_bev",
    "validate_boxes",
    "bev_iou",
    "bev_iou_pairs",
    "nms_bev",
]


def wrap_angle(angle: np.ndarray | float) -> np.ndarray:
    """Wrap angles (radians) to the half-open interval (-pi, pi]."""
    wrapped = np.mod(np.asarray(angle, dtype=float) + np.pi, 2.0 * np.pi) - np.pi
    return np.where(wrapped <= -np.pi, wrapped + 2.0 * np.pi, wrapped)


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
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf; all values must be finite")
    if np.any(arr[:, 3:6] < 0):
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


def box_corners_bev(boxes: np.ndarray) -> np.ndarray:
    """BEV footprint corners (N, 4, 2) of boxes (N, 7), counter-clockwise."""
    boxes = np.asarray(boxes, dtype=float).reshape(-1, 7)
    local = _CORNER_SIGNS[None, :, :] * boxes[:, None, 3:5]
    c, s = np.cos(boxes[:, 6])[:, None], np.sin(boxes[:, 6])[:, None]
    x = boxes[:, None, 0] + c * local[..., 0] - s * local[..., 1]
    y = boxes[:, None, 1] + s * local[..., 0] + c * local[..., 1]
    return np.stack([x, y], axis=-1)


def _cross(o: np.ndarray, a: np.ndarray, p: np.ndarray) -> np.ndarray:
    """z of (a - o) x (p - o); positive when p is left of the directed line o->a."""
    return (a[..., 0] - o[..., 0]) * (p[..., 1] - o[..., 1]) - (a[..., 1] - o[..., 1]) * (
        p[..., 0] - o[..., 0]
    )


def _compact(points: np.ndarray, valid: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Move each row's valid points to the front, keeping their order; (P, size, 2)."""
    n_pairs = points.shape[0]
    slot = np.cumsum(valid, axis=1) - 1
    rows, cols = np.nonzero(valid)
    out = np.zeros((n_pairs, size, 2))
    out[rows, slot[rows, cols]] = points[rows, cols]
    count = valid.sum(axis=1)
    return out, np.arange(size)[None, :] < count[:, None]


def _convex_intersection_area(subject: np.ndarray, clip: np.ndarray) -> np.ndarray:
    """Area of the intersection of convex quads, pair by pair.

    subject, clip: (P, 4, 2) counter-clockwise corners. Sutherland-Hodgman
    clipping, vectorised over pairs with fixed-size vertex buffers and a
    validity mask (written by hand: shapely is exact but works one pair at a
    time, far too slow for the thousands of pairs per frame the metric needs).
    """
    n_pairs = subject.shape[0]
    rows = np.arange(n_pairs)[:, None]
    poly, valid = subject, np.ones((n_pairs, 4), dtype=bool)
    for edge in range(4):
        a = clip[:, edge][:, None, :]
        b = clip[:, (edge + 1) % 4][:, None, :]
        count = valid.sum(axis=1, keepdims=True)
        idx = np.arange(poly.shape[1])[None, :]
        nxt_pts = poly[rows, np.where(idx + 1 < count, idx + 1, 0)]
        s_cur, s_nxt = _cross(a, b, poly), _cross(a, b, nxt_pts)
        in_cur, in_nxt = s_cur >= 0.0, s_nxt >= 0.0
        crosses = (in_cur != in_nxt) & valid
        t = (s_cur / np.where(crosses, s_cur - s_nxt, 1.0))[..., None]
        inter = poly + t * (nxt_pts - poly)
        # Each vertex emits itself (if inside) then the crossing point (if any).
        emitted = np.stack([poly, inter], axis=2).reshape(n_pairs, -1, 2)
        emitted_valid = np.stack([in_cur & valid, crosses], axis=2).reshape(n_pairs, -1)
        poly, valid = _compact(emitted, emitted_valid, 4 + edge + 1)
    # Shoelace over the valid vertices, closing each polygon on its first vertex.
    count = valid.sum(axis=1, keepdims=True)
    idx = np.arange(poly.shape[1])[None, :]
    nxt_pts = poly[rows, np.where(idx + 1 < count, idx + 1, 0)]
    terms = poly[..., 0] * nxt_pts[..., 1] - nxt_pts[..., 0] * poly[..., 1]
    area = 0.5 * np.where(valid, terms, 0.0).sum(axis=1)
    return np.where(count[:, 0] >= 3, np.maximum(area, 0.0), 0.0)


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
    inter = _convex_intersection_area(box_corners_bev(boxes_a), box_corners_bev(boxes_b))
    union = area_a + area_b - inter
    return np.where(union > 0.0, inter / np.where(union > 0.0, union, 1.0), 0.0)


def bev_iou(boxes_a: np.ndarray, boxes_b: np.ndarray) -> np.ndarray:
    """Exact IoU (N, M) between the BEV footprints of boxes_a (N, 7) and boxes_b (M, 7).

    Pairs whose circumscribed circles do not overlap are skipped (IoU 0), so
    sparse scenes cost little more than the distance test.
    """
    boxes_a = validate_boxes(boxes_a, "boxes_a")
    boxes_b = validate_boxes(boxes_b, "boxes_b")
    iou = np.zeros((boxes_a.shape[0], boxes_b.shape[0]))
    if iou.size == 0:
        return iou
    radius_a = 0.5 * np.hypot(boxes_a[:, 3], boxes_a[:, 4])
    radius_b = 0.5 * np.hypot(boxes_b[:, 3], boxes_b[:, 4])
    gap = np.hypot(
        boxes_a[:, None, 0] - boxes_b[None, :, 0], boxes_a[:, None, 1] - boxes_b[None, :, 1]
    )
    ia, ib = np.nonzero(gap < radius_a[:, None] + radius_b[None, :])
    if ia.size:
        iou[ia, ib] = _pair_iou(boxes_a[ia], boxes_b[ib])
    return iou


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
