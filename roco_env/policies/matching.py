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
:func:`pose_features`. RoCo's re-matching rounds of one collaborator against one landmark
set match inside their compiled loop (:func:`~roco_env.policies.pose_kernels.attempt_rounds`):
per-box features are computed once, and S_edge is reused while the candidate pairs and
the initial matches stay the same (it does not depend on the pose otherwise).
:func:`match_star_graphs` is one such matching on its own (the tests' and the ablation
checks' entry).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from roco_env.policies.pose_kernels import MatchSettings, empty_match_cache, scored_pairs
from roco_env.schema import spec

__all__ = [
    "MatchingParams",
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


def match_star_graphs(
    landmarks: np.ndarray, boxes_own: np.ndarray, boxes_ego: np.ndarray, params: MatchingParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Match landmarks (L, 3) to a collaborator's boxes: one compiled matching
    (:func:`~roco_env.policies.pose_kernels.scored_pairs`; module docstring).

    landmarks in the ego frame; boxes_own (K, 3): box poses in the collaborator's frame;
    boxes_ego (K, 3): the same boxes in the ego frame under the current pose estimate.
    Returns (landmark index (P,), box index (P,), similarity S (P,)), sorted by landmark
    index.
    """
    if landmarks.shape[0] == 0 or boxes_own.shape[0] == 0:
        return _EMPTY_INDEX, _EMPTY_INDEX, np.zeros(0)
    pairs, edge = empty_match_cache()
    land, box, score, _ = scored_pairs(
        np.ascontiguousarray(landmarks[:, :2], dtype=float),
        np.ascontiguousarray(np.asarray(boxes_ego)[:, :2], dtype=float),
        float(params.tau2),
        pose_features(landmarks),
        pose_features(boxes_own),
        tuple(params.match_settings()),
        (tuple(pairs), edge),  # plain tuples: pose_kernels' module docstring
    )
    return land, box, score
