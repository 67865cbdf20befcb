"""V2I-Calib (Qu et al., IROS 2024) and V2I-Calib++ (arXiv 2410.11008), re-implemented.

Both register two agents from their boxes alone: every ego box i paired with every
collaborator box k hypothesises the transform that lays box k onto box i,

    T_ik = B_i R(f) B_k^{-1}        (B = the box's SE(2) pose; f in {0, pi}),

the second heading f = pi because detectors flip headings. The *affinity* of (i, k) is
how well the rest of the two scenes agree under T_ik, an "overall" score summed over
the boxes around the anchors:

    A[i, k] = max_f  sum_{m in N(i)} max_{n in N(k)} s(L_i(m), L_{k,f}(n))

with L_i(m) box m in the frame of box i (and L_{k,f}(n) box n in the frame of box k
turned by f), so a pair is scored without mapping whole scenes. ``metric`` picks s:

* ``"oiou"`` (V2I-Calib's overall IoU): s = BEV IoU of the two footprints;
* ``"odist"`` (V2I-Calib++'s overall distance, the default): s = max(0, 1 - d^2 / r^2),
  r = ``odist_threshold`` m and d the centre distance, and 0 when the headings differ
  by more than ``inlier_yaw_deg`` (modulo pi). The paper measures box distance on box
  vertices; a centre distance with a heading gate is our choice (the vertex distance
  of two same-size boxes is a function of these two), and it scores all K x M anchors
  in one compiled loop (the pi turn only negates the collaborator's local centres).

Choices the papers leave open or that we made for speed, each a parameter:
``neighbors`` (the N(i): each box's nearest boxes, None = all boxes; the papers use all
boxes of the frame, which costs O(K^2 M^2)); ``min_affinity`` (an association needs at
least this affinity, in units of agreeing boxes).

Association: ``"hungarian"`` (V2I-Calib: maximum-weight one-to-one assignment on A,
scipy's Kuhn-Munkres) or ``"sinkhorn"`` (V2I-Calib++'s optimal transport: entropic OT
on A / ``sinkhorn_epsilon`` with a dustbin row and column scored ``min_affinity``, as
in SuperGlue, ``sinkhorn_iterations`` log-domain iterations; pairs that are each
other's best transport partner are kept). Extrinsic estimate: the affinity-weighted SVD
(Kabsch) fit on the associated box centres, then as alternatives the best distinct
single-pair transforms of every anchor pair with at least ``min_affinity`` (associated
or not); the shared refinement (re-association + SVD, robust least squares) and
do-no-harm rule of :mod:`roco_env.policies.prior_free` stand in for the papers'
optimisation stage. The papers are V2I (vehicle to roadside unit); nothing here
assumes which agent is which.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from roco_env.geometry import bev_iou_pairs, se2_compose, se2_inverse
from roco_env.policies.prior_free import (
    PriorFreeParams,
    PriorFreePolicy,
    Proposer,
    aligner,
    distinct_top,
    fit_se2,
)
from roco_env.policies.prior_free_kernels import odist_scores
from roco_env.schema import spec

__all__ = ["V2ICalibParams", "V2ICalibPolicy", "affinity_matrix", "sinkhorn", "v2i_calib_align",
           "v2i_calib_search"]

METRICS = ("odist", "oiou")
ASSOCIATIONS = ("sinkhorn", "hungarian")
_FAR = 1e6  # coordinate of padding neighbours: never close to anything


@dataclass(frozen=True)
class V2ICalibParams(PriorFreeParams):
    """V2I-Calib(++) parameters on top of :class:`PriorFreeParams` (module docstring)."""

    metric: str = spec("odist", choices=METRICS, doc="box-pair distance of the affinity")
    association: str = spec("sinkhorn", choices=ASSOCIATIONS,
                            doc="how the affinity becomes matches")
    neighbors: int | None = spec(6, low=1, doc="neighbours of a box's local frame (None: "
                                 "all boxes)")
    odist_threshold: float = spec(2.0, low=0.0, low_open=True,
                                  doc="r of the odist score, m")
    min_affinity: float = spec(2.0, low=0.0, low_open=True,
                               doc="affinity an association needs (agreeing "
                               "boxes)")
    sinkhorn_epsilon: float = spec(0.1, low=0.0, low_open=True,
                                   doc="Sinkhorn runs on affinity / "
                                   "sinkhorn_epsilon")
    sinkhorn_iterations: int = spec(50, low=1, doc="Sinkhorn iterations")


def _local_neighbours(boxes: np.ndarray, count: int | None) -> tuple[np.ndarray, np.ndarray]:
    """Each box's ``count`` nearest other boxes in that box's frame: (K, N, 3) poses
    (x, y, yaw) and (K, N) indices (-1 and far away where a box has fewer neighbours)."""
    k = boxes.shape[0]
    n = k - 1 if count is None else min(int(count), k - 1)
    if n <= 0:
        return np.full((k, 0, 3), _FAR), np.zeros((k, 0), dtype=np.int64)
    _, near = cKDTree(boxes[:, :2]).query(boxes[:, :2], k=n + 1)
    near = np.asarray(near).reshape(k, n + 1)[:, 1:]
    local = se2_compose(se2_inverse(boxes[:, [0, 1, 6]])[:, None, :], boxes[near][..., [0, 1, 6]])
    return local, near


def affinity_matrix(ego: np.ndarray, own: np.ndarray, p: V2ICalibParams,
                    ego_neighbours: tuple[np.ndarray, np.ndarray] | None = None,
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Affinity A (M, K) of every (ego box, collaborator box) anchor pair and the heading
    flip f (M, K) in {0, pi} that achieves it. ego (M, 7) / own (K, 7) boxes;
    ego_neighbours: the ego's ``_local_neighbours`` when already computed."""
    ego_local, ego_near = ego_neighbours or _local_neighbours(ego, p.neighbors)
    own_local, own_near = _local_neighbours(own, p.neighbors)
    m, k = ego.shape[0], own.shape[0]
    if ego_local.shape[1] == 0 or own_local.shape[1] == 0:
        return np.zeros((m, k)), np.zeros((m, k))
    if p.metric == "odist":
        scores = _odist(ego_local, own_local, p)
    else:
        scores = [_oiou(ego, own, ego_local, own_local, ego_near, own_near, f)
                  for f in (0.0, np.pi)]
    flipped = scores[1] > scores[0]
    return np.where(flipped, scores[1], scores[0]), np.where(flipped, np.pi, 0.0)


def _odist(ego_local: np.ndarray, own_local: np.ndarray,
           p: V2ICalibParams) -> tuple[np.ndarray, np.ndarray]:
    """sum_m max_n max(0, 1 - d^2/r^2) [heading gate] for all anchors, unturned and
    turned by pi (turning negates the collaborator's local centres; the gate is modulo
    pi, so it is the same for both)."""
    def doubled(local: np.ndarray) -> np.ndarray:
        # cos(2 (yaw_a - yaw_b)) >= cos(2 gate) <=> heading difference modulo pi within gate.
        return np.stack([np.cos(2.0 * local[..., 2]), np.sin(2.0 * local[..., 2])], axis=-1)

    return odist_scores(np.ascontiguousarray(ego_local), np.ascontiguousarray(own_local),
                        doubled(ego_local), doubled(own_local), 1.0 / p.odist_threshold**2,
                        float(np.cos(2.0 * np.deg2rad(min(p.inlier_yaw_deg, 45.0)))))


def _oiou(ego: np.ndarray, own: np.ndarray, ego_local: np.ndarray, own_local: np.ndarray,
          ego_near: np.ndarray, own_near: np.ndarray, flip: float) -> np.ndarray:
    """sum_m max_n BEV IoU of the neighbours' footprints in the anchors' frames (only
    pairs whose centres are closer than the sum of their half-diagonals can overlap)."""
    m, n, _ = ego_local.shape
    k, q, _ = own_local.shape
    turned = se2_compose(np.array([0.0, 0.0, flip]), own_local)
    dx = ego_local[:, :, None, None, 0] - turned[None, None, :, :, 0]
    dy = ego_local[:, :, None, None, 1] - turned[None, None, :, :, 1]
    reach = np.hypot(ego[:, 3], ego[:, 4])[ego_near][:, :, None, None] / 2 + (
        np.hypot(own[:, 3], own[:, 4])[own_near][None, None, :, :] / 2)
    cand = np.nonzero(dx * dx + dy * dy < reach * reach)
    iou = np.zeros((m, n, k, q))
    if cand[0].size:
        ia, ja, ib, jb = cand
        box_a = ego[ego_near[ia, ja]].copy()
        box_a[:, [0, 1, 6]] = ego_local[ia, ja]
        box_b = own[own_near[ib, jb]].copy()
        box_b[:, [0, 1, 6]] = turned[ib, jb]
        iou[cand] = bev_iou_pairs(box_a, box_b)
    return iou.max(axis=3).sum(axis=1)


def sinkhorn(scores: np.ndarray, dustbin: float, iterations: int) -> np.ndarray:
    """Log transport plan (M + 1, K + 1) of entropic optimal transport with a dustbin.

    scores (M, K) are log-affinities; the dustbin row/column scores ``dustbin``; row
    marginals 1 for each of the M rows and K for the dustbin row, column marginals 1 and
    M likewise (every box either matches or goes to the dustbin). Alternating
    normalisation (scipy has no optimal-transport solver; the loop is a few vectorised
    lines).
    """
    m, k = scores.shape
    coupling = np.full((m + 1, k + 1), float(dustbin))
    coupling[:m, :k] = scores
    # Scaling form of the iterations on exp(coupling - max): the same fixed point as the
    # log-domain updates at a fraction of their cost; the shift keeps exp finite.
    kernel = np.exp(coupling - coupling.max())
    mu = np.concatenate([np.ones(m), [k]])
    nu = np.concatenate([np.ones(k), [m]])
    a, b = np.ones(m + 1), np.ones(k + 1)
    tiny = np.finfo(float).tiny
    # BLAS products, not a compiled loop: in symmetric layouts (a line of equally spaced
    # boxes) transport partners tie exactly and a different summation order flips them.
    row, col = np.empty(m + 1), np.empty(k + 1)
    for _ in range(int(iterations)):
        np.divide(mu, np.maximum(np.dot(kernel, b, out=row), tiny, out=row), out=a)
        np.divide(nu, np.maximum(np.dot(kernel.T, a, out=col), tiny, out=col), out=b)
    return np.log(np.maximum(kernel * a[:, None] * b[None, :], tiny))


def _associate(affinity: np.ndarray, p: V2ICalibParams) -> tuple[np.ndarray, np.ndarray]:
    """Associated (ego index, own index) pairs with affinity >= min_affinity."""
    if p.association == "hungarian":
        rows, cols = linear_sum_assignment(affinity, maximize=True)
    else:
        plan = sinkhorn(affinity / p.sinkhorn_epsilon, p.min_affinity / p.sinkhorn_epsilon,
                        p.sinkhorn_iterations)[:-1, :-1]
        rows = np.arange(plan.shape[0])
        cols = plan.argmax(axis=1)
        mutual = plan.argmax(axis=0)[cols] == rows
        rows, cols = rows[mutual], cols[mutual]
    keep = affinity[rows, cols] >= p.min_affinity
    return rows[keep], cols[keep]


def v2i_calib_search(ego_boxes: np.ndarray, p: V2ICalibParams) -> Proposer:
    """The V2I-Calib proposer for ego boxes (M, 7): collaborator boxes (K, 7) ->
    candidate T_{j->i} (H, 3), best first. The ego's neighbourhoods are formed once."""
    ego_neighbours = _local_neighbours(ego_boxes, p.neighbors)
    ego = ego_boxes[:, [0, 1, 6]]

    def propose(own_boxes: np.ndarray) -> np.ndarray:
        affinity, flip = affinity_matrix(ego_boxes, own_boxes, p, ego_neighbours)
        rows, cols = _associate(affinity, p)
        if rows.size == 0:
            return np.zeros((0, 3))
        own = own_boxes[:, [0, 1, 6]]
        # the alternatives come from every anchor pair the affinity admits, not only the
        # associated ones: in a periodic layout pairs one period apart tie exactly, the
        # association keeps one of them by index, and the rival shift must still be heard
        # by the do-no-harm rule (which pair wins a tie must not decide the outcome)
        pair_rows, pair_cols = np.nonzero(affinity >= p.min_affinity)
        turned = own[pair_cols].copy()
        turned[:, 2] += flip[pair_rows, pair_cols]
        single = se2_compose(ego[pair_rows], se2_inverse(turned))
        top = distinct_top(single, affinity[pair_rows, pair_cols], p.max_candidates, p)
        candidates = single[top]
        if rows.size >= 2:
            fit = fit_se2(own[cols, :2], ego[rows, :2], affinity[rows, cols])
            candidates = np.vstack([fit, candidates])
        return candidates

    return propose


v2i_calib_align = aligner(v2i_calib_search, V2ICalibParams, "v2i_calib",
                          "Correct the collaborators' relative poses with V2I-Calib(++).")


class V2ICalibPolicy(PriorFreePolicy):
    """V2I-Calib(++) as an env policy: ``V2ICalibPolicy(**params)(obs) -> action (N, 3)``."""

    ALIGN = staticmethod(v2i_calib_align)
    PARAMS = V2ICalibParams
    METHOD = "v2i_calib"
