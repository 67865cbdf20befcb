"""What the prior-free aligners (RANSAC, V2I-Calib, FreeAlign) share.

Each prior-free method proposes *candidate* relative poses T_{j->i} from the boxes
alone (no use of the reported pose); this module turns candidates into a decision,
the same way for every method so that they differ only in how they search:

1. **refinement** (:func:`refine_pose`): associate the collaborator's boxes with the
   ego's under the candidate (one-to-one nearest centres within ``refine_gate`` m,
   headings compared modulo pi because detectors flip headings), re-fit the pose to
   the associated centres in closed form (weighted Kabsch/Umeyama in SE(2), i.e. the
   SVD of the 2x2 cross-covariance), repeat ``refine_iterations`` times; the chosen
   candidate gets a final robust least-squares solve on the box poses (the pose
   graph's single-vertex Levenberg-Marquardt with the box-uncertainty information and
   the robust kernel, :func:`roco_env.policies.posegraph.optimize_pose`);
2. **consensus** (:func:`consensus`, :func:`support`): the one-to-one inliers under a
   pose, a box pair being an inlier when its centres are within ``inlier_distance`` m
   and its headings within ``inlier_yaw_deg`` degrees (modulo pi), and their soft
   support sum exp(-d^2 / (2 ``support_sigma``^2)) (d the centre distance): a pose that
   lays boxes exactly on each other outscores one that explains as many loosely (a
   lane of cars slid by one car);
3. the candidate with the highest support is the estimate;
4. **do-no-harm** (``do_no_harm=True``, the default; False applies the estimate
   whenever one exists, to measure the raw method): the reported pose is kept when
   (a) the estimate has fewer than ``min_inliers`` inliers; (b) the estimate lies
   within ``distinct_distance`` m and ``distinct_yaw_deg`` deg of the reported pose:
   the boxes do not say the prior is off (the estimate's own error, a few
   centimetres from box noise, would otherwise replace an exact prior); or (c)
   another *distinct* pose explains nearly as many boxes: a refined candidate or the
   refined reported pose itself that differs from the estimate by more than
   ``distinct_distance`` m or ``distinct_yaw_deg`` deg and has at least
   ``ambiguity_ratio`` times its support. (c) is the ratio test of feature matching
   applied to whole poses: in a periodic layout (a parking row) several shifts explain
   the boxes equally well and the evidence cannot pick one; and when the reported
   pose is distinct from the estimate yet explains the boxes as well, nothing says
   the prior is wrong.

Frames: the ego's reported frame (ego = identity); collaborator boxes in their own
frame; metres and radians. Agent index convention: 0 = ego, j + 1 = collaborator j.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from roco_env.geometry import wrap_angle
from roco_env.policies.adapter import ArrayAlignmentPolicy
from roco_env.policies.base import AlignmentResult
from roco_env.policies.landmarks import (
    AlignmentInputs,
    UncertaintyParams,
    params_from_kwargs,
    prepare_inputs,
)
from roco_env.policies.posegraph import ROBUST_KERNELS, optimize_pose
from roco_env.policies.prior_free_kernels import (
    Gates,
    Placement,
    fit_se2_kernel,
    gated_pairs,
    refine_rounds,
    suppress,
)
from roco_env.schema import spec

__all__ = [
    "CandidateSearch",
    "PriorFreeParams",
    "PriorFreePolicy",
    "Proposer",
    "aligner",
    "axial_difference",
    "consensus",
    "content_seed",
    "distinct_top",
    "fit_se2",
    "poses_distinct",
    "prior_free_align",
    "refine_pose",
    "support",
]

# A candidate search maps (ego boxes (M, 7), params) to a proposer: a function of one
# collaborator's boxes (K, 7) in its own frame returning candidate T_{j->i} (H, 3), best
# first by the method's own ranking. The ego side (pairs, neighbourhoods, distances) is
# prepared once per frame and shared by every collaborator.
Proposer = Callable[[np.ndarray], np.ndarray]
CandidateSearch = Callable[[np.ndarray, "PriorFreeParams"], Proposer]

_EMPTY = np.zeros(0, dtype=np.int64)


@dataclass(frozen=True)
class PriorFreeParams(UncertaintyParams):
    """Parameters every prior-free method shares (module docstring; units m, deg unless
    noted). distinct_distance and distinct_yaw_deg serve rules (b) and (c) of do-no-harm
    and the candidates' non-maximum suppression."""

    do_no_harm: bool = spec(True, doc="keep the reported pose when the evidence is weak "
                            "(False: apply the method's estimate whenever it has one)")
    min_inliers: int = spec(3, low=1, doc="inliers the estimate needs under do-no-harm")
    inlier_distance: float = spec(1.5, low=0.0, low_open=True,
                                  doc="consensus gate of a box pair, m")
    inlier_yaw_deg: float = spec(10.0, low=0.0, low_open=True,
                                 doc="consensus gate of a box pair, deg")
    refine_gate: float = spec(3.0, low=0.0, low_open=True,
                              doc="association gate of the refinement rounds, m")
    refine_iterations: int = spec(3, low=0, doc="association + Kabsch rounds per candidate")
    max_candidates: int = spec(3, low=1, doc="candidates (best first) refined and compared")
    support_sigma: float = spec(0.3, low=0.0, low_open=True,
                                doc="scale of the soft support that ranks candidates "
                                "and rule (c), m")
    ambiguity_ratio: float = spec(0.8, low=0.0, high=1.0, low_open=True, doc="rule (c)")
    distinct_distance: float = spec(0.5, low=0.0, low_open=True,
                                    doc="poses closer than this and distinct_yaw_deg are the "
                                    "same hypothesis, m")
    distinct_yaw_deg: float = spec(1.0, low=0.0, low_open=True,
                                   doc="see distinct_distance, deg")
    robust_kernel: str | None = spec("cauchy", choices=(*ROBUST_KERNELS, None),
                                     doc="robust kernel of the final least-squares solve "
                                     "(as roco's)")
    kernel_delta: float = spec(float(np.sqrt(7.815)), low=0.0, low_open=True,
                               doc="the kernel's width in whitened units")
    max_solver_iterations: int = spec(100, low=1,
                                      doc="Levenberg-Marquardt cap of the final solve")


def axial_difference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """|a - b| for headings known up to pi (detectors flip them), in [0, pi/2] rad."""
    d = np.mod(np.asarray(a) - np.asarray(b), np.pi)
    return np.minimum(d, np.pi - d)


def content_seed(*arrays: np.ndarray) -> int:
    """A seed computed from the arrays' bytes: the same inputs always draw the same
    samples, so a method that samples stays a deterministic function of its input."""
    crc = 0
    for arr in arrays:
        crc = zlib.crc32(np.ascontiguousarray(arr, dtype=np.float64).tobytes(), crc)
    return crc


def fit_se2(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Least-squares SE(2) pose T (3,) with dst ~= T * src for points (P, 2), P >= 2.

    Closed form: the rotation maximises trace(R^T C) for the weighted cross-covariance
    C of the centred points (SVD of C with the reflection excluded; in 2-D this is
    atan2 of C's antisymmetric and symmetric parts), then t = mean_dst - R mean_src.
    """
    w = np.ones(src.shape[0]) if weights is None else np.asarray(weights, dtype=float)
    return fit_se2_kernel(np.ascontiguousarray(src, dtype=float),
                          np.ascontiguousarray(dst, dtype=float), w / w.sum())


def _associate(
    pose: np.ndarray, ego: np.ndarray, own: np.ndarray, gate: float, yaw_gate: float | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One-to-one association of own boxes (mapped by ``pose``) to ego boxes: pairs
    within ``gate`` m (and ``yaw_gate`` rad modulo pi when given); where several boxes
    compete for one, the minimum total centre distance (Hungarian) decides.
    Returns (ego index, own index, distance)."""
    if ego.shape[0] == 0 or own.shape[0] == 0:
        return _EMPTY, _EMPTY, np.zeros(0)
    yaw = float(pose[2])
    placement = Placement(float(pose[0]), float(pose[1]), float(np.cos(yaw)), float(np.sin(yaw)),
                          yaw)
    gates = Gates(float(gate), -1.0 if yaw_gate is None else float(yaw_gate))
    rows, cols, dist2, one_to_one = gated_pairs(tuple(placement), ego, own, tuple(gates))
    if one_to_one:
        return rows, cols, np.sqrt(dist2)
    cost = np.full((ego.shape[0], own.shape[0]), 1e6)
    cost[rows, cols] = np.sqrt(dist2)
    ok = np.zeros(cost.shape, dtype=bool)
    ok[rows, cols] = True
    r, c = linear_sum_assignment(cost)
    keep = ok[r, c]
    return r[keep], c[keep], cost[r[keep], c[keep]]


def consensus(
    pose: np.ndarray, ego: np.ndarray, own: np.ndarray, p: PriorFreeParams
) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one inlier pairs (ego index, own index) under ``pose`` (module docstring)."""
    e, o, _ = _associate(pose, ego, own, p.inlier_distance, np.deg2rad(p.inlier_yaw_deg))
    return e, o


def support(pose: np.ndarray, ego: np.ndarray, own: np.ndarray,
            p: PriorFreeParams) -> tuple[int, float]:
    """(inlier count, soft support sum_inliers exp(-d^2 / (2 support_sigma^2))) of
    ``pose``, d the inlier's centre distance (m)."""
    _, _, dist = _associate(pose, ego, own, p.inlier_distance, np.deg2rad(p.inlier_yaw_deg))
    return dist.size, float(np.exp(-0.5 * (dist / p.support_sigma) ** 2).sum())


def refine_pose(pose: np.ndarray, ego: np.ndarray, own: np.ndarray,
                p: PriorFreeParams) -> np.ndarray:
    """``refine_iterations`` rounds of association within ``refine_gate`` + Kabsch fit, in
    compiled rounds (:func:`~roco_env.policies.prior_free_kernels.refine_rounds`) that
    pause at a round whose boxes compete: its association is the Hungarian assignment made
    here (:func:`_associate`), with which they go on."""
    pose = np.asarray(pose, dtype=float).copy()
    gate, yaw_gate = float(p.refine_gate), float(np.deg2rad(p.inlier_yaw_deg))
    gates = tuple(Gates(gate, yaw_gate))
    pose, done, paused = refine_rounds(pose, ego, own, gates, int(p.refine_iterations), None)
    remaining = int(p.refine_iterations) - done
    while paused:
        e, o, _ = _associate(pose, ego, own, gate, yaw_gate)
        pose, done, paused = refine_rounds(pose, ego, own, gates, remaining, (e, o))
        remaining -= done
    return pose


def distinct_top(poses: np.ndarray, scores: np.ndarray, count: int,
                 p: PriorFreeParams) -> np.ndarray:
    """Indices of up to ``count`` highest-scoring poses (H, 3), each distinct
    (:func:`poses_distinct`) from every better one kept (non-maximum suppression)."""
    return suppress(np.ascontiguousarray(poses, dtype=float),
                    np.argsort(-np.asarray(scores, dtype=float), kind="stable"), int(count),
                    float(p.distinct_distance), float(np.deg2rad(p.distinct_yaw_deg)))


def poses_distinct(a: np.ndarray, b: np.ndarray, p: PriorFreeParams) -> np.ndarray:
    """Whether poses a (..., 3) and b (..., 3) are distinct hypotheses: farther apart
    than ``distinct_distance`` m or ``distinct_yaw_deg`` deg."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return (np.hypot(a[..., 0] - b[..., 0], a[..., 1] - b[..., 1]) > p.distinct_distance) | (
        np.abs(wrap_angle(a[..., 2] - b[..., 2])) > np.deg2rad(p.distinct_yaw_deg))


@dataclass
class _SlotOutcome:
    pose: np.ndarray
    applied: bool
    pairs: tuple[np.ndarray, np.ndarray]
    candidates: int = 0
    solver: int = 0
    reason: str = ""


def _final_solve(pose: np.ndarray, ego: np.ndarray, own: np.ndarray, info: np.ndarray,
                 p: PriorFreeParams) -> tuple[np.ndarray, int]:
    """Robust least squares of the pose on its inlier box poses (headings of flipped
    boxes turned by pi so the yaw residual measures the real misfit)."""
    e, o = consensus(pose, ego, own, p)
    if e.size < 2:
        return pose, 0
    measured = own[o].copy()
    flip = np.abs(wrap_angle(ego[e, 2] - measured[:, 2] - pose[2])) > np.pi / 2
    measured[flip, 2] = wrap_angle(measured[flip, 2] + np.pi)
    fit = optimize_pose(pose, ego[e], measured, info[o], kernel=p.robust_kernel,
                        kernel_delta=p.kernel_delta, max_iterations=p.max_solver_iterations)
    return fit.pose, fit.iterations


def _align_slot(ego_boxes: np.ndarray, own_boxes: np.ndarray, info: np.ndarray,
                reported: np.ndarray, propose: Proposer | None,
                p: PriorFreeParams) -> _SlotOutcome:
    keep = _SlotOutcome(reported, False, (_EMPTY, _EMPTY))
    if min(ego_boxes.shape[0], own_boxes.shape[0]) < 2:
        count = min(ego_boxes.shape[0], own_boxes.shape[0])
        keep.reason = f"{count} boxes: an SE(2) pose needs >= 2"
        return keep
    ego, own = ego_boxes[:, [0, 1, 6]], own_boxes[:, [0, 1, 6]]
    candidates = np.asarray(propose(own_boxes), dtype=float).reshape(-1, 3)
    candidates = candidates[: p.max_candidates]
    keep.candidates = candidates.shape[0]
    if candidates.shape[0] == 0:
        keep.reason = "no pose hypothesis"
        return keep
    refined = np.array([refine_pose(c, ego, own, p) for c in candidates])
    supports = [support(r, ego, own, p) for r in refined]
    best = int(np.argmax([score for _, score in supports]))
    estimate, (n_best, s_best) = refined[best], supports[best]
    if p.do_no_harm:
        if n_best < p.min_inliers:
            keep.reason = f"{n_best} inliers < min_inliers={p.min_inliers}"
            return keep
        if not poses_distinct(estimate, reported, p):
            keep.reason = ("estimate within distinct_distance / distinct_yaw_deg of the "
                           "reported pose: no evidence that the prior is off")
            return keep
        prior = refine_pose(reported, ego, own, p)
        rivals = [*zip(refined, supports, strict=True), (prior, support(prior, ego, own, p))]
        for rival, (_, score) in rivals:
            if poses_distinct(rival, estimate, p) and score >= p.ambiguity_ratio * s_best:
                keep.reason = (f"ambiguous: a distinct pose has support {score:.2f} of the "
                               f"estimate's {s_best:.2f} (ambiguity_ratio={p.ambiguity_ratio})")
                return keep
    elif n_best < 2:
        keep.reason = f"{n_best} inliers: an SE(2) pose needs >= 2"
        return keep
    pose, solver = _final_solve(estimate, ego, own, info, p)
    return _SlotOutcome(pose, True, consensus(pose, ego, own, p), keep.candidates, solver)


def prior_free_align(
    ego_boxes: np.ndarray,
    ego_unc: np.ndarray,
    collab_boxes: Sequence[np.ndarray],
    collab_unc: Sequence[np.ndarray],
    reported: np.ndarray,
    search: CandidateSearch,
    params_cls: type,
    params: dict,
    method: str,
) -> AlignmentResult:
    """Align every collaborator to the ego with the candidate ``search`` of a method.

    Same array call as :func:`roco_env.policies.roco.roco_align` (boxes (K, 7) and
    uncertainties (K, 3) per agent in its own frame, reported (N, 3) T_{j->i}); params:
    fields of ``params_cls`` (a :class:`PriorFreeParams`). ``matched_pairs`` lists the
    inlier (ego box, collaborator box) pairs of the applied estimates; ``landmarks`` the
    matched ego boxes' poses; ``outer_iterations`` the refined candidates;
    ``solver_iterations`` the Levenberg-Marquardt iterations.
    """
    p = params_from_kwargs(params_cls, params, method)
    inputs: AlignmentInputs = prepare_inputs(ego_boxes, ego_unc, collab_boxes, collab_unc,
                                             reported, p)
    n = inputs.n_collaborators
    corrected = inputs.reported.copy()
    applied = np.zeros(n, dtype=bool)
    pairs, reasons = [], []
    outer = solver = 0
    boxes = [np.asarray(b, dtype=float).reshape(-1, 7) for b in [ego_boxes, *collab_boxes]]
    ego = inputs.poses[0]
    # _align_slot needs no proposer when the ego has too few boxes for a pose.
    propose = search(boxes[0], p) if boxes[0].shape[0] >= 2 else None
    for j in range(n):
        out = _align_slot(boxes[0], boxes[j + 1], inputs.information[j + 1],
                          inputs.reported[j], propose, p)
        outer, solver = outer + out.candidates, solver + out.solver
        if out.reason:
            reasons.append(f"slot {j}: {out.reason}")
        if not out.applied:
            continue
        corrected[j], applied[j] = out.pose, True
        e, o = out.pairs
        pairs.append(np.stack([np.full(e.size, -1), e, np.full(e.size, j), o], axis=1))
    matched = np.concatenate(pairs).astype(np.int64) if pairs else np.zeros((0, 4), np.int64)
    return AlignmentResult(
        corrected=corrected,
        applied=applied,
        matched_pairs=matched,
        landmarks=ego[np.unique(matched[:, 1])],
        outer_iterations=outer,
        solver_iterations=solver,
        reason="; ".join(reasons),
    )


def aligner(search: CandidateSearch, params_cls: type, method: str,
            summary: str) -> Callable[..., AlignmentResult]:
    """The array aligner ``align(ego_boxes, ego_unc, collab_boxes, collab_unc, reported,
    **params) -> AlignmentResult`` of a prior-free method (its candidate ``search`` and
    parameter class); ``summary`` opens its docstring."""

    def align(ego_boxes: np.ndarray, ego_unc: np.ndarray, collab_boxes: Sequence[np.ndarray],
              collab_unc: Sequence[np.ndarray], reported: np.ndarray,
              **params) -> AlignmentResult:
        return prior_free_align(ego_boxes, ego_unc, collab_boxes, collab_unc, reported,
                                search, params_cls, params, method)

    align.__name__ = align.__qualname__ = f"{method}_align"
    align.__doc__ = (
        f"{summary}\n\nSame array call as :func:`roco_env.policies.roco.roco_align`; params: "
        f"fields of :class:`{params_cls.__name__}`. The reported poses are used only by "
        "the do-no-harm rule."
    )
    return align


class PriorFreePolicy(ArrayAlignmentPolicy):
    """Env policy of a prior-free aligner: ``Policy(**params)(obs, info=None) -> action
    (N, 3)``. Subclasses set ``ALIGN`` (a staticmethod), ``PARAMS`` and ``METHOD``."""

    ALIGN: Callable[..., AlignmentResult]
    PARAMS: type = PriorFreeParams
    METHOD: str = ""

    def __init__(self, **params) -> None:
        super().__init__(type(self).ALIGN, params_from_kwargs(self.PARAMS, params, self.METHOD),
                         params)
