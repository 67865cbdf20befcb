"""Box-correspondence RANSAC: the plain geometric floor of the prior-free aligners.

Minimal sample = two box correspondences (i <-> k, j <-> l), ego boxes i, j and
collaborator boxes k, l. The two centre pairs fix an SE(2) hypothesis

    theta = atan2(e_j - e_i) - atan2(c_l - c_k),   t = (e_i + e_j)/2 - R(theta) (c_k + c_l)/2

(e ego centres, c collaborator centres in its own frame). Instead of drawing
correspondences blindly, samples are restricted to pairs of box pairs that agree on
the SE(2)-invariants of a box pair (the hypotheses a blind draw would reject anyway):

* the centre distance: | |e_j - e_i| - |c_l - c_k| | <= ``pair_tolerance`` m, with
  pair lengths in [``min_pair_distance``, ``max_pair_distance``] m (short pairs give
  ill-conditioned rotations);
* with ``use_yaw_invariants``: the relative heading of the two boxes and the bearing
  of the segment in the first box's frame agree within ``yaw_tolerance_deg`` (both
  modulo pi: detectors flip headings).

Pairs are formed between each box and its ``pair_neighbors`` nearest boxes (None:
all pairs): neighbours are the boxes both agents most likely see together, and the
restriction keeps the search linear in the box count. Every ordered ego pair is
tried against every unordered collaborator pair. When more
than ``max_hypotheses`` consistent samples exist, ``max_hypotheses`` of them are drawn
without replacement with a generator seeded from the boxes' bytes
(:func:`roco_env.policies.prior_free.content_seed`): the same observation always gives
the same answer. Each hypothesis is scored by its inlier count (collaborator boxes
whose mapped centre has an ego box within ``inlier_distance`` m with heading within
``inlier_yaw_deg``, not one-to-one: the usual RANSAC score), counted on at most
``score_boxes`` collaborator boxes spread over its list (None = all; the ranking only
has to find the right basin, the refinement recounts on every box); the best distinct
hypotheses (non-maximum suppression, ``distinct_distance`` / ``distinct_yaw_deg``) go
to the shared refinement (re-association + SVD fit, robust least squares) and
do-no-harm rule of :mod:`roco_env.policies.prior_free`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from roco_env.policies.prior_free import (
    PriorFreeParams,
    PriorFreePolicy,
    Proposer,
    aligner,
    content_seed,
    distinct_top,
)
from roco_env.policies.prior_free_kernels import (
    Gates,
    PairInvariants,
    Placement,
    inlier_counts,
    matching_pairs,
)
from roco_env.schema import spec

__all__ = ["RansacParams", "RansacPolicy", "ransac_align", "ransac_search"]


@dataclass(frozen=True)
class RansacParams(PriorFreeParams):
    """RANSAC parameters (m, deg) on top of :class:`PriorFreeParams` (module docstring)."""

    pair_tolerance: float = spec(0.6, low=0.0, low_open=True,
                                 doc="two box pairs' centre distances agree "
                                 "within this, m")
    min_pair_distance: float = spec(4.0, low=0.0, low_open=True,
                                    doc="shortest box pair that votes, m")
    max_pair_distance: float = spec(80.0, doc="longest box pair that votes, m "
                                    "(> min_pair_distance)")
    use_yaw_invariants: bool = spec(True, doc="pairs must also agree in relative "
                                    "heading and bearing")
    yaw_tolerance_deg: float = spec(10.0, low=0.0, low_open=True,
                                    doc="tolerance of those invariants, deg "
                                    "(modulo pi)")
    max_hypotheses: int = spec(200, low=1, doc="consistent samples drawn at most")
    pair_neighbors: int | None = spec(8, low=1, doc="each box pairs with this many nearest "
                                      "boxes (None: all pairs)")
    score_boxes: int | None = spec(24, low=2, doc="collaborator boxes a hypothesis's "
                                   "inliers are counted on (None: all)")

    def __post_init__(self) -> None:
        """The rule joining fields (each field's own: its spec)."""
        PriorFreeParams.__post_init__(self)
        if not self.max_pair_distance > self.min_pair_distance:
            raise ValueError(f"max_pair_distance must be > min_pair_distance="
                             f"{self.min_pair_distance}; got {self.max_pair_distance}")


def _pairs(poses: np.ndarray, ordered: bool, p: RansacParams) -> tuple:
    """Box pairs (first, second) with their length, relative heading and bearing: each
    box with its ``pair_neighbors`` nearest boxes (None: all pairs), both orders when
    ``ordered``, else each unordered pair once."""
    k = poses.shape[0]
    if p.pair_neighbors is None or p.pair_neighbors >= k - 1:
        a, b = np.triu_indices(k, 1)
    else:
        _, near = cKDTree(poses[:, :2]).query(poses[:, :2], k=int(p.pair_neighbors) + 1)
        first = np.repeat(np.arange(k), int(p.pair_neighbors))
        second = near[:, 1:].ravel()
        code = np.unique(np.minimum(first, second) * k + np.maximum(first, second))
        a, b = code // k, code % k
    if ordered:
        a, b = np.concatenate([a, b]), np.concatenate([b, a])
    d = poses[b, :2] - poses[a, :2]
    length = np.hypot(d[:, 0], d[:, 1])
    keep = (length >= p.min_pair_distance) & (length <= p.max_pair_distance)
    a, b, d, length = a[keep], b[keep], d[keep], length[keep]
    angle = np.arctan2(d[:, 1], d[:, 0])
    return a, b, length, poses[b, 2] - poses[a, 2], angle - poses[a, 2], angle


def ransac_search(ego_boxes: np.ndarray, p: RansacParams) -> Proposer:
    """The RANSAC proposer for ego boxes (M, 7): collaborator boxes (K, 7) -> candidate
    T_{j->i} (H, 3), best first. The ego's ordered pairs are formed once per frame."""
    ego = ego_boxes[:, [0, 1, 6]]
    ea, eb, elen, erel, ebear, eang = _pairs(ego, True, p)
    order = np.argsort(elen)
    ego_pairs = tuple(PairInvariants(elen[order], erel[order], ebear[order]))  # by length
    yaw_tol = float(np.deg2rad(p.yaw_tolerance_deg)) if p.use_yaw_invariants else -1.0
    tolerance = tuple(Gates(float(p.pair_tolerance), yaw_tol))
    inlier_gates = tuple(Gates(float(p.inlier_distance), float(np.deg2rad(p.inlier_yaw_deg))))

    def propose(own_boxes: np.ndarray) -> np.ndarray:
        own = own_boxes[:, [0, 1, 6]]
        ca, cb, clen, crel, cbear, cang = _pairs(own, False, p)
        if elen.size == 0 or clen.size == 0:
            return np.zeros((0, 3))
        ego_idx, own_idx = matching_pairs(ego_pairs, order,
                                          tuple(PairInvariants(clen, crel, cbear)), tolerance)
        if ego_idx.size == 0:
            return np.zeros((0, 3))
        if ego_idx.size > p.max_hypotheses:
            rng = np.random.default_rng(content_seed(ego, own))
            pick = np.sort(rng.choice(ego_idx.size, size=int(p.max_hypotheses), replace=False))
            ego_idx, own_idx = ego_idx[pick], own_idx[pick]
        theta = eang[ego_idx] - cang[own_idx]
        c, s = np.cos(theta), np.sin(theta)
        e_mid = (ego[ea[ego_idx], :2] + ego[eb[ego_idx], :2]) / 2.0
        c_mid = (own[ca[own_idx], :2] + own[cb[own_idx], :2]) / 2.0
        tx = e_mid[:, 0] - (c * c_mid[:, 0] - s * c_mid[:, 1])
        ty = e_mid[:, 1] - (s * c_mid[:, 0] + c * c_mid[:, 1])
        scored = own
        if p.score_boxes is not None and own.shape[0] > p.score_boxes:
            scored = own[np.linspace(0, own.shape[0] - 1, int(p.score_boxes)).astype(int)]
        scores = inlier_counts(tuple(Placement(tx, ty, c, s, theta)), ego, scored, inlier_gates)
        poses = np.column_stack([tx, ty, theta])
        top = distinct_top(poses, scores.astype(float), p.max_candidates, p)
        return poses[top]

    return propose


ransac_align = aligner(ransac_search, RansacParams, "ransac",
                       "Correct the collaborators' relative poses by box-correspondence RANSAC.")


class RansacPolicy(PriorFreePolicy):
    """RANSAC as an env policy: ``RansacPolicy(**params)(obs, info=None) -> action (N, 3)``."""

    ALIGN = staticmethod(ransac_align)
    PARAMS = RansacParams
    METHOD = "ransac"
