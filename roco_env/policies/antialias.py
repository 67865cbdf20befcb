"""RoCo made robust to aliasing: explicit pose hypotheses before RoCo's matching.

Repetitive layouts (rows of parked cars 2.5 m apart) let RoCo's matcher converge to
a global shift of the truth by one stall and its significance test then *confirms*
the wrong, consistent correction. :func:`antialias_align` adds a decision stage in
front of :func:`~roco_env.policies.roco.roco_align`, per collaborator j:

1. hypotheses for T_{j->i}: the strongest rotation + translation votes of nearby box
   pairs within ``search_radius`` of the reported pose, the reported pose itself and,
   when given, the temporal track's prediction; when the rotation vote lands more than
   ``distinct_r_deg`` from the reported rotation, also the strongest translation vote at
   the reported rotation (a heading vote degrees off, along a straight road seen by two
   RSUs 118 m apart, left only aliases among the peaks); each refined by matching and a
   robust pose solve against the ego's boxes (:mod:`roco_env.policies.hypotheses`);
2. each hypothesis h gets the score (chi-square units, -2 ln of a likelihood ratio)
   ``S(h) = evidence(h) - d(h, reported)^T P d(h, reported) - d(h, track)^T Q d(h, track)``
   with evidence from box pairs (position, heading modulo pi, log size), free space and
   mutual detections, P from ``prior_sigma_t`` / ``prior_sigma_r_deg`` and Q from the
   track's age (``track_sigma_t`` / ``track_sigma_r_deg`` per step);
3. the best hypothesis is trusted only when it beats the best *distinct* one (more than
   ``distinct_t`` m or ``distinct_r_deg`` deg away) by ``min_margin``; then it becomes
   the starting point of RoCo's matching rounds; when the margin is too small the
   collaborator is left out of RoCo and keeps its reported pose (do no harm);
4. (``use_ambiguity``) the best hypothesis is also diagnosed
   (:func:`~roco_env.policies.ambiguity.diagnose`): which directions of the pose the boxes
   (and the track) determine without the reported pose's prior. A hypothesis that wins
   only thanks to that prior (a lattice alias, a shift along an evenly spaced queue) is
   not trusted: the collaborator is left out of RoCo, and its pose keeps the reported one
   along the undetermined directions and takes the best hypothesis's determined part
   (:meth:`~roco_env.policies.ambiguity.Ambiguity.projected`), if that part wins by
   ``min_margin``, is significant (a Wald test with the pairs' information at RoCo's
   ``significance``) and, when the pairs' fit is thin, is worth ``min_margin`` of that
   information (:meth:`~roco_env.policies.ambiguity.Ambiguity.move_statistic`, as in
   step 6); with nothing determined, or a translation the pairs themselves pin poorly, it
   keeps the reported pose. The diagnosis also looks ``BEYOND`` (2) times as far
   as the hypotheses (votes over twice ``search_radius``, four times ``max_hypotheses``
   peaks, refined alike): a pose there whose evidence beats the best hypothesis's by
   ``min_margin`` (scored together, on the boxes both can see) shows that the best one
   explains far less than the scene supports (a reported error beyond the search, the
   best hypothesis an alias near the reported pose); its shift is left open like a
   rival's, so the reported pose is kept along it. A best hypothesis supported by so few
   pairs that a candidate with one pair fewer than ``min_matches`` (too few to be a
   hypothesis) could come within ``min_margin`` of it (``outlier_chi2`` per extra pair:
   with the defaults 3 pairs) must also beat those candidates (the vote peaks and the
   reported pose refined with ``min_matches - 1`` pairs) by ``min_margin`` in evidence;
   one that does not, and that pairs other boxes (the pick's own pairs put it at least
   ``outlier_chi2`` per pair away), is a rival too (a sparse queue: the truth pairs 2
   boxes, an alias one car along it 3). The best hypothesis must also beat the reported
   pose where no hypothesis stands for it, by ``min_margin`` in score (the priors
   counted, as the decision's margin counts them): the reported pose as it stands and the
   seeds refined with ``min_matches - 1`` pairs, those of them that pair other boxes than
   the best (as above), scored together with it; else it is not trusted (the decision's
   margin is the smaller of the two). The decision's margin counts only the poses that
   refine with ``min_matches`` pairs, so an alias 5 m along packed rows that pairs 4 boxes
   (25 chi2 units of prior for the move) beat nothing and was trusted, where the reported
   pose, 0.3 m off with 2 pairs, scored as well;
5. (``use_track``) the track must not carry an alias the evidence rejects: when the pick
   made with the track's prior is beaten by another hypothesis's evidence alone by
   ``min_margin``, the decision is taken again without the track
   (:attr:`Decision.track_dropped`) and the policy forgets that track.

RoCo (unchanged, with all its parameters: the prior edges and the significance test still
refer to the reported poses) then matches and solves the joint pose graph from those
starting points.

6. (``use_ambiguity``) a collaborator without any hypothesis (nothing refines within the
   search: too few boxes shared with the ego, or a reported error beyond it) is one RoCo
   may place through the other collaborators' boxes alone. Its correction is applied only
   when the collaborator's own boxes support it: RoCo's pose must beat the reported one by
   ``min_margin`` in evidence (the two scored together against the ego's boxes,
   :attr:`Decision.support`). Otherwise the collaborator is left out of RoCo too and keeps
   its reported pose, and RoCo solves again without it (until no such collaborator is left).
   A trusted pick whose pairs' fit is thin (they pin the collaborator's origin to a
   translation std of ``THIN_FIT_T`` (0.3 m) or more,
   :attr:`~roco_env.policies.ambiguity.Ambiguity.translation_std`, and no better than one
   pair of its boxes pins its centre, ``THIN_FIT_BOXES`` times
   :attr:`~roco_env.policies.ambiguity.Ambiguity.box_std`) is held to the same
   margin by its own pairs: RoCo's pose must be worth ``min_margin`` of the pick's pairs'
   information over the reported pose
   (:meth:`~roco_env.policies.ambiguity.Ambiguity.move_statistic`, the Gaussian part of
   the evidence, with the evidence's pose slack); else the same. RoCo's significance test
   weighs the boxes' covariances alone at 1% false alarms, and a thin fit (3-4 boxes 60 m
   from two far-apart agents) that passes it moves a pose reported 0.1-0.2 m off by
   0.5-0.9 m.

:class:`AntiAliasPolicy` keeps one track per (ego, collaborator) agent-id pair from the
info dict (``info["agent"]`` and ``info["collaborators"]``), so one instance may serve
several agents; without those ids it uses no track. Call :meth:`AntiAliasPolicy.reset`
between episodes.
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from dataclasses import dataclass, fields, replace
from functools import lru_cache

import numpy as np

from roco_env.geometry import wrap_angle
from roco_env.policies.adapter import ArrayAlignmentPolicy, ObservationView
from roco_env.policies.ambiguity import Ambiguity, diagnose, scaled_offsets
from roco_env.policies.base import AlignmentResult
from roco_env.policies.hypotheses import (
    BoxSet,
    EvidenceParams,
    box_sets,
    evidence_terms,
    generate_hypotheses,
    refine_terms,
    score_hypotheses,
    translation_peaks,
)
from roco_env.policies.hypothesis_kernels import decision_margin
from roco_env.policies.landmarks import params_from_kwargs, prepare_inputs
from roco_env.policies.pose_kernels import refine_starts
from roco_env.policies.prior_free import poses_distinct
from roco_env.policies.roco import RoCoParams, roco_solve
from roco_env.schema import spec

__all__ = ["AntiAliasParams", "AntiAliasPolicy", "Decision", "antialias_align"]

# How many times the hypotheses' translation search (``search_radius``) the search for
# better explanations beyond it reaches (module docstring, step 4).
BEYOND = 2.0

# When a fit counts as thin (:func:`_thin`): its correction must then be worth
# ``min_margin`` of its pairs' information (module docstring, steps 4 and 6). A
# translation std (m) at the collaborator's origin of at least THIN_FIT_T and at least
# THIN_FIT_BOXES times the boxes' own precision (Ambiguity.box_std: one ego box and one
# collaborator box, their centres' stds summed in quadrature). Measured on the stress
# search's scenes: the fits that made a pose > 0.5 m worse were 0.43-1.1 m thin, the fits
# of corrections that pass RoCo's test only 0.1-0.45 m (the benchmarks' none above 0.3 m).
# The absolute bound alone also holds back paper_table1_calibrated's corrections (boxes of
# 0.3 m std, box_std 0.46-0.56 m): the fits it blocked there (std >= 0.3 m, worth < 20)
# were 0.30-0.84 m, overlapping the harmful ones, but only 0.56-1.72 box_std (median 0.71,
# 34 of 259 at 1 or more), while the RSU-pair stress scenes' were 0.93-5.3 box_std (box_std
# 0.23-0.39 m; 23 of 24 at 1 or more; the one below, let through, harms nothing there). A
# fit that pins the origin no better than one pair of boxes pins its centre is thin.
THIN_FIT_T = 0.3
THIN_FIT_BOXES = 1.0


@dataclass(frozen=True)
class AntiAliasParams(RoCoParams, EvidenceParams):
    """RoCo's parameters, the evidence ones (:class:`EvidenceParams`) and the decision's.

    use_hypotheses: the decision stage (False = plain RoCo). min_margin: chi2 units the
    best hypothesis must beat the best distinct one by (ln likelihood ratio =
    min_margin / 2). distinct_t (m) / distinct_r_deg (deg): when two hypotheses are
    distinct. use_track: the temporal prior;
    track_sigma_t (m) / track_sigma_r_deg (deg): std of its prediction per step of age;
    track_max_age: steps a track survives without a decision. use_ambiguity: the
    diagnosis of step 4 (module docstring; False = the decision alone).
    """

    use_hypotheses: bool = spec(True, doc="the decision stage (False: plain RoCo)")
    min_margin: float = spec(20.0, low=0.0, low_open=True,
                             doc="chi2 units the best hypothesis must beat the best distinct "
                             "one by")
    distinct_t: float = spec(1.0, low=0.0, low_open=True,
                             doc="translation apart (m) that makes two hypotheses distinct")
    distinct_r_deg: float = spec(1.0, low=0.0, low_open=True,
                                 doc="rotation apart (deg) that makes two hypotheses distinct")
    use_track: bool = spec(True, doc="the temporal prior of the track")
    track_sigma_t: float = spec(0.5, low=0.0, low_open=True,
                                doc="std of the track's prediction per step of age, m")
    track_sigma_r_deg: float = spec(1.0, low=0.0, low_open=True,
                                    doc="std of the track's prediction per step of age, deg")
    track_max_age: int = spec(10, low=1, doc="steps a track survives without a decision")
    use_ambiguity: bool = spec(True, doc="the ambiguity diagnosis (step 4; False: the "
                               "decision alone)")

    # The names under which :func:`~roco_env.policies.prior_free.poses_distinct` reads the
    # distinctness thresholds (m, deg).
    @property
    def distinct_distance(self) -> float:
        return self.distinct_t

    @property
    def distinct_yaw_deg(self) -> float:
        return self.distinct_r_deg


_ROCO_FIELDS = tuple(f.name for f in fields(RoCoParams))


@dataclass(frozen=True)
class Decision:
    """The decision stage's outcome for one collaborator.

    pose (3,) or None: the chosen hypothesis (None = ambiguous, not determined in every
    direction, or no evidence);
    margin: its score minus the best distinct hypothesis's or, when smaller, minus the
    reported pose's where no hypothesis stands for it (step 4 of the module docstring;
    chi2 units; nan when nothing was scored); hypotheses: how many were scored (0: too few boxes to match, RoCo
    runs from the reported pose); ambiguity: the diagnosis of the best hypothesis
    (:class:`~roco_env.policies.ambiguity.Ambiguity`; None when nothing was scored or
    ``use_ambiguity`` is off); track_dropped: the track's prediction was given but its pick
    was overruled by the evidence (step 5 of the module docstring), so the decision was
    taken without it and the track is to be forgotten; support: for a pose RoCo corrected,
    how much better RoCo's pose explains the collaborator's boxes than the reported pose
    does (chi2 units; below ``min_margin`` the correction is not applied: step 6 of the
    module docstring): with no hypothesis the evidence difference, with a trusted pick of a
    thin fit the move's worth by the pick's pairs' information; NaN otherwise.
    """

    pose: np.ndarray | None
    margin: float
    hypotheses: int
    ambiguity: Ambiguity | None = None
    track_dropped: bool = False
    support: float = float("nan")


@lru_cache(maxsize=16)
def _decision_terms(p: AntiAliasParams) -> tuple:
    """The settings of ``p`` as the compiled decision stage takes them, computed once per
    parameter set: the refinement's (:func:`~roco_env.policies.hypotheses.refine_terms`),
    the evidence's (:func:`~roco_env.policies.hypotheses.evidence_terms`), the reported
    pose prior's variances (m^2, rad^2), the track's std per step of age (m, rad) and the
    distinctness thresholds (m, rad)."""
    sigma_r = np.deg2rad(p.prior_sigma_r_deg)
    return (
        refine_terms(p, p.robust_kernel, p.kernel_delta, p.min_matches),
        evidence_terms(p),
        (float(p.prior_sigma_t**2), float(sigma_r**2)),
        (p.track_sigma_t, np.deg2rad(p.track_sigma_r_deg)),
        (float(p.distinct_t), float(np.deg2rad(p.distinct_r_deg))),
    )


@lru_cache(maxsize=16)
def _wide_search(p: AntiAliasParams) -> EvidenceParams:
    """The evidence settings of ``p`` with ``BEYOND`` times its translation search: the
    search beyond the hypotheses' (module docstring, step 4)."""
    return EvidenceParams(**{f.name: getattr(p, f.name) for f in fields(EvidenceParams)}
                          | {"search_radius": BEYOND * p.search_radius,
                             "max_hypotheses": int(BEYOND**2 * p.max_hypotheses)})


def _beyond_search(
    ego: BoxSet, collab: BoxSet, reported: np.ndarray, poses: np.ndarray, best: int,
    p: AntiAliasParams,
) -> np.ndarray:
    """Poses (R, 3) beyond the hypotheses ``poses`` (H, 3) that explain the boxes far
    better than ``poses[best]`` (module docstring, step 4): the vote peaks of a search
    ``BEYOND`` times as wide around ``reported`` (3,), refined as the hypotheses are, that
    are distinct from every hypothesis and whose evidence beats the best's by ``min_margin``
    (scored together with it, on the boxes both can see)."""
    peaks = generate_hypotheses(ego, collab, reported, _wide_search(p))
    far = refine_starts(peaks, np.zeros((0, 3)), ego.poses, collab.poses, collab.information,
                        _decision_terms(p)[0])
    far = far[poses_distinct(far[:, None], poses, p).all(axis=1)]
    if far.shape[0] == 0:
        return far
    evidence = score_hypotheses(ego, collab, np.concatenate([poses[best:best + 1], far]), p)
    return far[evidence[1:] >= evidence[0] + p.min_margin]


@lru_cache(maxsize=16)
def _weak_refine(p: AntiAliasParams) -> tuple:
    """The refinement's settings of ``p`` with one pair fewer than ``min_matches``: the
    candidates too weakly matched to be hypotheses (module docstring, step 4)."""
    return refine_terms(p, p.robust_kernel, p.kernel_delta, p.min_matches - 1)


def _few_pairs(matches: int, p: AntiAliasParams) -> bool:
    """Whether a pose supported by ``matches`` pairs may fail to beat a candidate with one
    pair fewer than ``min_matches`` by ``min_margin``: its extra pairs' gain, at most
    ``outlier_chi2`` each (chi2 units), stays below the margin (module docstring, step 4;
    with the defaults: at most 3 pairs)."""
    return p.min_matches > 1 and p.outlier_chi2 * (matches - p.min_matches + 1) < p.min_margin


def _weak_candidates(
    ego: BoxSet, collab: BoxSet, peaks: np.ndarray, seeds: np.ndarray, ambiguity: Ambiguity,
    p: AntiAliasParams,
) -> np.ndarray:
    """Candidates (R, 3) that the hypotheses' ``min_matches`` left out and that pair other
    boxes than the diagnosed pose (module docstring, step 4): the vote ``peaks`` (H, 3) and
    ``seeds`` (S, 3) refined with one pair fewer, as :func:`_apart` keeps them."""
    weak = refine_starts(peaks, seeds, ego.poses, collab.poses, collab.information,
                         _weak_refine(p))
    return _apart(weak, ambiguity, p)


def _apart(candidates: np.ndarray, ambiguity: Ambiguity, p: AntiAliasParams) -> np.ndarray:
    """The ``candidates`` (R, 3) distinct from the diagnosed pose ``ambiguity.pose`` (3,)
    that its own pairs put at least ``outlier_chi2`` per pair away (``d^T A d``, A their
    information :attr:`~roco_env.policies.ambiguity.Ambiguity.information`): nearer, a
    candidate re-fits those pairs within the boxes' noise rather than pairing other boxes."""
    pose = ambiguity.pose
    candidates = candidates[poses_distinct(candidates[:, None], pose[None], p).all(axis=1)]
    offset = scaled_offsets(candidates, pose, ambiguity.scale)
    apart = np.einsum("ri,ij,rj->r", offset, ambiguity.information, offset)
    return candidates[apart >= p.outlier_chi2 * ambiguity.matches]


def _weak_rivals(ego: BoxSet, collab: BoxSet, pose: np.ndarray, weak: np.ndarray,
                 p: AntiAliasParams) -> np.ndarray:
    """The weak candidates ``weak`` (R, 3) (:func:`_weak_candidates`) whose evidence comes
    within ``min_margin`` of that of ``pose`` (3,) (scored together, chi2 units): they
    explain the boxes about as well by other pairs (module docstring, step 4)."""
    if weak.shape[0] == 0:
        return weak
    evidence = score_hypotheses(ego, collab, np.concatenate([pose[None], weak]), p)
    return weak[evidence[1:] >= evidence[0] - p.min_margin]


def _reported_margin(
    ego: BoxSet, collab: BoxSet, ambiguity: Ambiguity, reported: np.ndarray,
    seeds: np.ndarray, track: np.ndarray | None, priors: tuple, p: AntiAliasParams,
) -> float:
    """How much the pick ``ambiguity.pose`` (3,) beats the reported pose where no hypothesis
    stands for it (module docstring, step 4): its score minus the best score of the
    reported pose (3,) as it stands and the ``seeds`` (S, 3: the reported pose, the track's
    prediction) refined with one pair fewer than ``min_matches``, those of them that
    :func:`_apart` keeps, all scored together with the decision's priors (the reported
    pose's, the ``track``'s; chi2 units); inf when none is kept."""
    weak = refine_starts(np.zeros((0, 3)), seeds, ego.poses, collab.poses, collab.information,
                         _weak_refine(p))
    others = _apart(np.concatenate([reported[None], weak]), ambiguity, p)
    if others.shape[0] == 0:
        return float("inf")
    terms = _decision_terms(p)
    _, _, scores, _ = decision_margin(
        ego.terms, collab.terms, np.concatenate([ambiguity.pose[None], others]), reported,
        track, terms[1], priors, terms[4])
    return float(scores[0] - scores[1:].max())


def _overruled(ego: BoxSet, collab: BoxSet, poses: np.ndarray, best: int,
               p: AntiAliasParams) -> bool:
    """Whether another hypothesis of ``poses`` (H, 3) explains the boxes better than
    ``poses[best]`` by ``min_margin`` (evidence alone, chi2 units): the pick of a prior
    (the track's) that the evidence overrules (module docstring, step 5)."""
    evidence = score_hypotheses(ego, collab, poses, p)
    return bool(evidence.max() >= evidence[best] + p.min_margin)


def _decide(
    ego: BoxSet,
    collab: BoxSet,
    reported: np.ndarray,
    track: tuple[np.ndarray, float] | None,
    p: AntiAliasParams,
) -> Decision:
    """Steps 1-3 of the module docstring for one collaborator: the vote peaks
    (:func:`~roco_env.policies.hypotheses.generate_hypotheses`; when their rotation is more
    than ``distinct_r_deg`` from the reported one, the strongest translation peak at the
    reported rotation too, :func:`~roco_env.policies.hypotheses.translation_peaks`); with
    the reported pose and the track's prediction, refined in one compiled pass
    (:func:`~roco_env.policies.pose_kernels.refine_starts`: a seed within 0.5 m / 0.5 deg
    of a peak would refine to the same pose and is skipped; a refined pose within 0.3 m /
    0.3 deg of an earlier one is dropped); evidence, priors and margin in another
    (:func:`~roco_env.policies.hypothesis_kernels.decision_margin`); then the best one's
    diagnosis (step 4) from those scores: rivals by the scores without the reported
    pose's prior (the track's kept), the determined part's margin with it."""
    refine, evidence, prior, (track_t, track_r), distinct = _decision_terms(p)
    reported = np.ascontiguousarray(reported, dtype=float)
    peaks = generate_hypotheses(ego, collab, reported, p)
    if peaks.shape[0] and abs(wrap_angle(peaks[0, 2] - reported[2])) > distinct[1]:
        peaks = np.concatenate([peaks, translation_peaks(ego, collab, reported, p, most=1)])
    if track is None:
        centre, seeds, priors = reported, reported[None], prior + (1.0, 1.0)
    else:
        centre, age = np.ascontiguousarray(track[0], dtype=float), track[1]
        seeds = np.stack([reported, centre])
        priors = prior + (float((track_t * age) ** 2), float((track_r * age) ** 2))
    poses = refine_starts(peaks, seeds, ego.poses, collab.poses, collab.information, refine)
    if poses.shape[0] == 0:
        return Decision(None, float("nan"), 0)
    best, margin, scores, unreported = decision_margin(
        ego.terms, collab.terms, poses, reported, None if track is None else centre, evidence,
        priors, distinct,
    )
    if track is not None and _overruled(ego, collab, poses, int(best), p):
        return replace(_decide(ego, collab, reported, None, p), track_dropped=True)
    ambiguity = None
    if p.use_ambiguity:
        beyond = _beyond_search(ego, collab, reported, poses, int(best), p)
        ambiguity = diagnose(ego, collab, poses, int(best), unreported, scores, p,
                             slack=evidence[:2], beyond=beyond)
        if ambiguity.matches >= p.min_matches:
            if _few_pairs(ambiguity.matches, p):
                weak = _weak_rivals(ego, collab, poses[best],
                                    _weak_candidates(ego, collab, peaks, seeds, ambiguity, p), p)
                if weak.shape[0]:
                    ambiguity = diagnose(ego, collab, poses, int(best), unreported, scores, p,
                                         slack=evidence[:2],
                                         beyond=np.concatenate([beyond, weak]))
            margin = min(margin, _reported_margin(ego, collab, ambiguity, reported, seeds,
                                                  None if track is None else centre, priors, p))
    trusted = margin >= p.min_margin and (ambiguity is None or ambiguity.determined == 3)
    return Decision(poses[best] if trusted else None, float(margin), poses.shape[0], ambiguity)


def _thin(ambiguity: Ambiguity) -> bool:
    """Whether the diagnosed pairs pin the collaborator's origin thinly: a translation std
    of at least ``THIN_FIT_T`` and at least ``THIN_FIT_BOXES`` times the boxes' own
    precision (:attr:`~roco_env.policies.ambiguity.Ambiguity.box_std`; the absolute bound
    alone where that is unknown)."""
    bound = THIN_FIT_T
    if np.isfinite(ambiguity.box_std):
        bound = max(bound, THIN_FIT_BOXES * ambiguity.box_std)
    return bool(ambiguity.translation_std >= bound)


def _worth(ambiguity: Ambiguity, reported: np.ndarray, pose: np.ndarray) -> float:
    """What the diagnosed pairs say for moving ``reported`` (3,) to ``pose`` (3,) (chi2
    units, :meth:`~roco_env.policies.ambiguity.Ambiguity.move_statistic`) when their fit
    is thin (:func:`_thin`); NaN (not asked) otherwise."""
    if not _thin(ambiguity):
        return float("nan")
    return ambiguity.move_statistic(reported, pose)


def _own_support(
    sets: Sequence[BoxSet], reported: np.ndarray, result: AlignmentResult,
    decisions: list[Decision], p: AntiAliasParams,
) -> list[Decision]:
    """Step 6 of the module docstring: ``decisions`` with :attr:`Decision.support` set for
    each collaborator whose pose RoCo corrected (``result``; NaN again where an earlier
    round's supported correction is no longer applied), chi2 units: without hypotheses the
    evidence of RoCo's pose minus that of the reported one (``reported`` (N, 3)), scored
    together on the collaborator's boxes against the ego's (``sets``: the ego's boxes, then
    each collaborator's); with a trusted pick the move's worth by its diagnosed pairs'
    information where their fit is thin (:func:`_worth`; NaN where it is not)."""
    supported = list(decisions)
    for j, decision in enumerate(decisions):
        if not result.applied[j]:
            # a support below min_margin is why the slot is out of RoCo (kept); a support
            # from an earlier round whose correction RoCo no longer applies is void
            if decision.support >= p.min_margin:
                supported[j] = replace(decision, support=float("nan"))
            continue
        if decision.hypotheses:
            # applied with hypotheses: a trusted pick, diagnosed (use_ambiguity)
            support = _worth(decision.ambiguity, reported[j], result.corrected[j])
        else:
            evidence = score_hypotheses(sets[0], sets[j + 1],
                                        np.stack([result.corrected[j], reported[j]]), p)
            support = float(evidence[0] - evidence[1])
        supported[j] = replace(decision, support=support)
    return supported


def _kept_out(
    decision: Decision, reported: np.ndarray, p: AntiAliasParams
) -> tuple[str, np.ndarray | None]:
    """Why a collaborator left out of RoCo keeps (part of) its reported pose (3,), and its
    projected pose (None: the reported pose is kept in full): step 4 of the module
    docstring when its diagnosis finds undetermined directions, else the margin's note."""
    ambiguity = decision.ambiguity
    if ambiguity is None or ambiguity.determined == 3:
        note = f"ambiguous (margin {decision.margin:.1f} < {p.min_margin:g}), reported pose kept"
        return note, None
    if not ambiguity.applicable:
        return f"{ambiguity.describe()}, reported pose kept", None
    pronoun = "it" if ambiguity.determined == 2 else "them"
    note = f"{ambiguity.describe()}, reported pose kept along {pronoun}"
    if not ambiguity.margin >= p.min_margin:
        return f"{note} and elsewhere (margin {ambiguity.margin:.1f} < {p.min_margin:g})", None
    if not ambiguity.significant(reported, p.significance):
        return f"{note}; the determined part is not significant", None
    projected = ambiguity.projected(reported)
    worth = _worth(ambiguity, reported, projected)
    if worth < p.min_margin:
        return (f"{note}; the determined part is worth only {worth:.1f} of its pairs' "
                f"information (< {p.min_margin:g})"), None
    return note, projected


def antialias_align(
    ego_boxes: np.ndarray,
    ego_unc: np.ndarray,
    collab_boxes: Sequence[np.ndarray],
    collab_unc: Sequence[np.ndarray],
    reported: np.ndarray,
    tracks: Sequence[tuple[np.ndarray, float] | None] | None = None,
    **params,
) -> tuple[AlignmentResult, list[Decision]]:
    """Correct the collaborators' relative poses (module docstring).

    Arrays as :func:`~roco_env.policies.roco.roco_align`; tracks: per collaborator None or
    (predicted T_{j->i} (3,), age in steps >= 1) from earlier decisions. params: fields of
    :class:`AntiAliasParams`. Returns the result and one :class:`Decision` per collaborator.
    """
    p = params_from_kwargs(AntiAliasParams, params, "roco_antialias")
    # RoCo's stage gets its own parameters (checked as roco_align checks them).
    roco_p = params_from_kwargs(
        RoCoParams, {k: v for k, v in params.items() if k in _ROCO_FIELDS}, "roco"
    )
    inputs = prepare_inputs(ego_boxes, ego_unc, collab_boxes, collab_unc, reported, p)
    n = inputs.n_collaborators
    if not p.use_hypotheses:
        return roco_solve(inputs, roco_p), [Decision(None, float("nan"), 0)] * n
    tracks = list(tracks) if tracks is not None and p.use_track else [None] * n
    if len(tracks) != n:
        raise ValueError(f"tracks must have one entry per reported pose ({n}); got {len(tracks)}")
    # prepare_inputs has validated the boxes; the sizes come from the same arrays.
    boxes = [np.asarray(b, dtype=float).reshape(-1, 7) for b in (ego_boxes, *collab_boxes)]
    sets = box_sets(boxes, inputs)
    start = inputs.reported.copy()
    decisions = []
    for j in range(n):
        decision = _decide(sets[0], sets[j + 1], inputs.reported[j], tracks[j], p)
        decisions.append(decision)
        if decision.pose is not None:
            start[j] = decision.pose
    ambiguous = [j for j, d in enumerate(decisions) if d.pose is None and d.hypotheses]
    # An ambiguous collaborator is left out of RoCo: it keeps its reported pose, or along
    # its undetermined directions only (step 4).
    result = roco_solve(inputs, roco_p, start, frozenset(ambiguous))
    # A collaborator without hypotheses is corrected by RoCo only where its own boxes
    # support the correction by min_margin; otherwise it is left out of RoCo too, with its
    # reported pose, and RoCo solves again without it (step 6).
    unsupported: list[int] = []
    while p.use_ambiguity:
        decisions = _own_support(sets, inputs.reported, result, decisions, p)
        more = [j for j, d in enumerate(decisions)
                if d.support < p.min_margin and j not in unsupported]
        if not more:
            break
        unsupported += more
        result = roco_solve(inputs, roco_p, start, frozenset(ambiguous + unsupported))
    corrected, applied = result.corrected.copy(), result.applied.copy()
    reasons = list(result.slot_reasons)
    for j in unsupported:
        reasons[j] = (f"RoCo's correction is worth only {decisions[j].support:.1f} of its "
                      f"hypothesis' pairs' information (< {p.min_margin:g}), reported pose kept"
                      if decisions[j].hypotheses else
                      f"no hypothesis within search_radius and RoCo's correction explains the "
                      f"boxes only {decisions[j].support:.1f} better than the reported pose "
                      f"(< {p.min_margin:g}), reported pose kept")
    for j in ambiguous:
        reasons[j], pose = _kept_out(decisions[j], inputs.reported[j], p)
        if pose is not None:
            corrected[j], applied[j] = pose, True
    reason = "; ".join(f"slot {j}: {r}" for j, r in enumerate(reasons) if r)
    return replace(result, corrected=corrected, applied=applied, reason=reason,
                   slot_reasons=tuple(reasons)), decisions


class AntiAliasPolicy(ArrayAlignmentPolicy):
    """``AntiAliasPolicy(**params)(obs, info=None) -> action (N, 3)``; tracks keyed by
    (``info["agent"]``, collaborator id) (module docstring). ``last_decisions`` holds the
    last call's :class:`Decision` per filled slot."""

    keeps_state = "per ego and collaborator (info['agent'], info['collaborators'])"

    def __init__(self, **params) -> None:
        checked = params_from_kwargs(AntiAliasParams, params, "roco_antialias")
        super().__init__(antialias_align, checked, params)
        self._tracks: dict[Hashable, list[tuple[int, np.ndarray]]] = {}
        self._steps: dict[Hashable, int] = {}
        self.last_decisions: list[Decision] = []

    def reset(self) -> None:
        """Forget every track (call between episodes)."""
        super().reset()
        self._tracks.clear()
        self._steps.clear()
        self.last_decisions = []

    @staticmethod
    def _ego_and_keys(info: dict | None, slots: np.ndarray) -> tuple[Hashable | None, list]:
        """The ego's id and the track key of each filled slot (None without ids)."""
        names = (info or {}).get("collaborators")
        ego = (info or {}).get("agent")
        if ego is None or names is None:
            return None, [None] * slots.size
        return ego, [(ego, names[s]) if s < len(names) else None for s in slots]

    def _prediction(self, key: Hashable | None, step: int) -> tuple[np.ndarray, float] | None:
        history = self._tracks.get(key) if key is not None else None
        if not history or step - history[-1][0] > self.params.track_max_age:
            return None
        last_step, last = history[-1]
        age = step - last_step
        if len(history) == 2:
            first_step, first = history[0]
            rate = (last - first) / (last_step - first_step)
            rate[2] = wrap_angle(last[2] - first[2]) / (last_step - first_step)
            last = last + rate * age
            last[2] = wrap_angle(last[2])
        return last, float(age)

    def align_view(
        self, view: ObservationView, observation: dict, info: dict | None
    ) -> AlignmentResult:
        """:func:`antialias_align` with each filled slot's track prediction; the decided
        poses extend the tracks."""
        ego, slot_keys = self._ego_and_keys(info, view.slots)
        step = self._steps.get(ego, 0) + 1
        if ego is not None:
            self._steps[ego] = step
        tracks = [self._prediction(k, step) for k in slot_keys]
        result, decisions = antialias_align(*view.arrays, tracks=tracks, **self._kwargs)
        for key, decision in zip(slot_keys, decisions, strict=True):
            if key is not None and decision.track_dropped:
                self._tracks.pop(key, None)
            if key is not None and decision.pose is not None:
                self._tracks[key] = [*self._tracks.get(key, [])[-1:], (step, decision.pose.copy())]
        self.last_decisions = decisions
        return result
