"""RoCo's graph-guided object matching (paper section 4.2; docs/alignment.md).

Given the landmark set P (poses in the ego frame) and one collaborator's boxes Q
(poses in the collaborator's own frame, and the same boxes mapped into the ego
frame with the current pose estimate):

1. star graph per box: centre = the box, leaves = the other boxes of the same set
   within ``neighbor_radius`` metres (the paper's "spatial neighbours"; default 20 m,
   None = all boxes). Local graphs matter with real detections: T_pm lives in box p's
   frame, so a heading error of p moves a leaf 50 m away by ~0.9 m per degree and the
   edge consistency of far leaves collapses (env urban_intersection at sigma 0.8:
   Success@1m1deg 0.70 with all boxes, 0.97 at 30 m, 0.996 at 20 m). Star graphs over
   all boxes help only in perfectly periodic layouts (tests/test_roco.py parking lot);
2. initial match A(m) = nearest q with dis(m, q) <= tau2 (centre distance, metres,
   in the ego frame);
3. edge similarity S_edge(p, q) = mean over leaves m of p with a match n = A(m),
   n != q and n a leaf of q, of exp(-||T_pm T_qn^{-1} - I||_F), T the 3x3
   homogeneous box-to-box transform (frame independent: T_qn is computed in the
   collaborator's own frame); 0 when no leaf qualifies;
4. distance similarity S_dis = exp(-dis(p, q)); S = S_edge + lambda * S_dis;
5. maximum-weight one-to-one assignment (Kuhn-Munkres) over the gated pairs
   (dis <= tau2); assigned pairs with S < tau1 are rejected. tau1 is set for the full
   S (maximum 1 + lambda); with a term switched off (ablation) the bar is scaled by the
   remaining terms' maximum (:attr:`MatchingParams.similarity_threshold`).

A matching is one compiled call (:func:`~roco_env.policies.pose_kernels.scored_pairs`):
the gate search, the (candidate pair x matched leaf) sums of S_edge and the assignment
(scipy's Kuhn-Munkres algorithm, step for step, when a landmark or a box has several
candidates). S_edge is a sum over the leaves of products of a candidate factor and a leaf
factor: with d_pm = t_m - t_p (ego frame), d_qn = t_n - t_q (own frame), u_m = yaw_m -
yaw_n and v_pq = yaw_p - yaw_q, ``||T_pm T_qn^{-1} - I||_F^2 = 4 (1 - cos(u_m - v_pq)) +
|d_pm|^2 + |d_qn|^2 - 2 d_pm^T R(u_m) d_qn``, every term a (C, 11) by (11, H) product of
:func:`pose_features`. :class:`StarGraphMatcher` serves the re-matching rounds of one
collaborator against one landmark set: per-box features are computed once, and S_edge is
reused while the candidate pairs and the initial matches stay the same (it does not
depend on the pose otherwise).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from roco_env.policies.pose_kernels import (
    MatchSettings,
    empty_match_cache,
    placed_centres,
    scored_pairs,
)
from roco_env.schema import spec

__all__ = [
    "MatchingParams",
    "StarGraphMatcher",
    "edge_consistency",
    "match_star_graphs",
    "pose_features",
]

_EMPTY_INDEX = np.zeros(0, dtype=np.int64)


@dataclass(frozen=True)
class MatchingParams:
    """The star-graph matcher's parameters (module docstring; S = S_edge + lam * S_dis)."""

    tau1: float = spec(0.5, doc="threshold of the full similarity S")
    tau2: float = spec(3.0, low=0.0, low_open=True, doc="gate of the initial nearest match, m")
    lam: float = spec(1.0, low=0.0, doc="weight of S_dis")
    use_edge_similarity: bool = spec(True, doc="S_edge on (ablation switch)")
    use_distance_similarity: bool = spec(True, doc="S_dis on (ablation switch)")
    neighbor_radius: float | None = spec(20.0, low=0.0, low_open=True,
                                         doc="radius of a star graph's leaves, m (None: "
                                         "every box is a leaf)")

    def __post_init__(self) -> None:
        """The rules joining fields (each field's own: its spec)."""
        if not (self.use_edge_similarity or self.use_distance_similarity):
            raise ValueError("use_edge_similarity and use_distance_similarity cannot both be False")
        if not (self.use_edge_similarity or self.lam > 0):
            raise ValueError("lam must be > 0 when use_edge_similarity is False (S = lam * S_dis)")

    @property
    def similarity_threshold(self) -> float:
        """The bar on S that tau1 sets for the terms switched on.

        tau1 is defined on the full S = S_edge + lam * S_dis, whose maximum is 1 + lam
        (S_edge, S_dis <= 1). Switching a term off removes its share of that maximum, so
        the bar is tau1 * (remaining maximum) / (1 + lam): every variant then asks for the
        same fraction tau1 / (1 + lam) of the score it can attain (0.25 at the defaults:
        S_edge >= 0.25 alone, or S_dis >= 0.25, i.e. dis <= ln 4 = 1.39 m, alone), and an
        ablation removes the term, not the term and half the acceptance band with it.
        """
        remaining = float(self.use_edge_similarity) + self.lam * float(self.use_distance_similarity)
        return self.tau1 * remaining / (1.0 + self.lam)

    def match_settings(self) -> MatchSettings:
        """The settings as the compiled matching takes them
        (:class:`~roco_env.policies.pose_kernels.MatchSettings`): weight of S_dis (0 = not
        used), use of S_edge, squared star-graph radius (m^2; -1 = no radius) and the bar
        on S (:attr:`similarity_threshold`)."""
        radius = self.neighbor_radius
        return MatchSettings(
            float(self.lam) if self.use_distance_similarity else 0.0,
            bool(self.use_edge_similarity),
            -1.0 if radius is None else float(radius) ** 2,
            float(self.similarity_threshold),
        )


def edge_consistency(rel_a: np.ndarray, rel_b: np.ndarray) -> np.ndarray:
    """exp(-||T_a T_b^{-1} - I||_F) for relative poses (..., 3) (closed form).

    For SE(2), T_a T_b^{-1} has rotation phi = yaw_a - yaw_b and translation
    t_a - R(phi) t_b; ||R(phi) - I||_F^2 = 4 (1 - cos phi).
    """
    return _consistency(*np.moveaxis(rel_a, -1, 0), *np.moveaxis(rel_b, -1, 0))


def _consistency(ax, ay, ayaw, bx, by, byaw):
    phi = ayaw - byaw
    c, s = np.cos(phi), np.sin(phi)
    tx = ax - (c * bx - s * by)
    ty = ay - (s * bx + c * by)
    return np.exp(-np.sqrt(4.0 * (1.0 - c) + tx * tx + ty * ty))


def pose_features(poses: np.ndarray) -> np.ndarray:
    """Per-pose factors (5, n) of the bilinear edge-similarity form: x, y, x^2 + y^2,
    cos(yaw), sin(yaw)."""
    x, y, yaw = poses[:, 0], poses[:, 1], poses[:, 2]
    return np.stack([x, y, x * x + y * y, np.cos(yaw), np.sin(yaw)])


class StarGraphMatcher:
    """Matching of one collaborator's boxes against a fixed landmark set, for several
    pose estimates (RoCo's re-matching rounds).

    landmarks (L, 3): poses in the ego frame; boxes_own (K, 3): the collaborator's box
    poses in its own frame; land_features (5, L) / box_features (5, K): their
    :func:`pose_features` when the caller keeps them (computed here otherwise).
    :meth:`match` takes the current pose estimate T_{j->i}.
    """

    def __init__(
        self,
        landmarks: np.ndarray,
        boxes_own: np.ndarray,
        params: MatchingParams,
        land_features: np.ndarray | None = None,
        box_features: np.ndarray | None = None,
    ):
        self.landmarks, self.boxes_own, self.params = landmarks, boxes_own, params
        self._land_features = (
            pose_features(landmarks) if land_features is None else land_features
        )
        self._land_xy = np.ascontiguousarray(landmarks[:, :2], dtype=float)
        self._box_features = pose_features(boxes_own) if box_features is None else box_features
        self._settings = tuple(params.match_settings())
        # S_edge of the last candidate pairs and initial matches (reused while they stay).
        pairs, edge = empty_match_cache()
        self._cache = tuple(pairs), edge

    def match(
        self, pose: np.ndarray, tau2: float | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Match under the pose estimate ``pose`` (3,) with gate ``tau2`` (m; default
        ``params.tau2``). Returns (landmark index (P,), box index (P,), similarity S (P,)),
        sorted by landmark index."""
        xy = placed_centres(np.asarray(pose, dtype=float), self.boxes_own)
        return self.match_centres(xy, self.params.tau2 if tau2 is None else tau2)

    def match_centres(
        self, centres: np.ndarray, tau2: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """As :meth:`match`, with the box centres (K, 2) already in the ego frame."""
        if self.landmarks.shape[0] == 0 or self.boxes_own.shape[0] == 0:
            return _EMPTY_INDEX, _EMPTY_INDEX, np.zeros(0)
        land, box, score, (pairs, edge) = scored_pairs(
            self._land_xy,
            np.ascontiguousarray(centres, dtype=float),
            float(tau2),
            self._land_features,
            self._box_features,
            self._settings,
            self._cache,
        )
        self._cache = tuple(pairs), edge  # plain tuples: pose_kernels' module docstring
        return land, box, score


def match_star_graphs(
    landmarks: np.ndarray, boxes_own: np.ndarray, boxes_ego: np.ndarray, params: MatchingParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Match landmarks (L, 3) to a collaborator's boxes.

    boxes_own (K, 3): box poses in the collaborator's frame; boxes_ego (K, 3): the same
    boxes in the ego frame under the current pose estimate. Returns (landmark index (P,),
    box index (P,), similarity S (P,)), sorted by landmark index.
    """
    matcher = StarGraphMatcher(landmarks, boxes_own, params)
    return matcher.match_centres(np.asarray(boxes_ego)[:, :2], params.tau2)
