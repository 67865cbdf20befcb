"""``defend``: reject the collaborators that lie, behind any aligner (docs/attacks.md).

``make_policy("defend", base="roco")`` (spec ``defend:base=roco``) acts in the env's
``gate`` action mode with the ``aligned`` observation (it declares both in
:attr:`Defend.env_overrides`; sweeps and ``EgoEnv`` merge them): the env runs the base
aligner, every collaborator's boxes arrive moved into the ego frame by its pose, and the
action keeps a collaborator with that pose (0) or rejects it (1), the explicit reject of
the gate mode (which solves the kept collaborators' poses again without the rejected ones).
Six tests, each a statistical test at level ``alpha``, and a re-test:

* **Correction** (temporal consistency): the base aligner's correction of a
  collaborator's reported pose (``shift_m``, ``turn_deg`` of the diagnostics), against
  the localisation noise assumed (``sigma_t`` m, ``sigma_r`` deg per agent and axis):
  ``q = shift^2 / s_t^2 + turn^2 / s_r^2`` with ``s_t^2 = 2 sigma_t^2 + 2 (d sigma_r)^2``
  (d the collaborator's distance, sigma_r in rad) and ``s_r^2 = 2 sigma_r^2`` is about
  chi-square with 3 dof for an honest collaborator. Two tests over its last ``window``
  steps, each at ``alpha / 2`` (Bonferroni): the sum of q against the chi-square
  quantile of 3 x steps dof (a jump fails at once, a slow drift once it has grown, any
  lie that changes from step to step), and the mean of the *signed* correction (an
  offset): ``c = reported^-1 * aligned`` is the correction in the collaborator's
  reported frame (x forward, y left; m, m, rad), where a fixed spoof stays fixed;
  whitened per step, ``z = (c_x / s_t, c_y / s_t, c_yaw / s_r)``, and
  ``|sum z|^2 / steps`` is chi-square with 3 dof for an honest collaborator with
  independent noise from step to step. The mean test has the power the sum lacks
  against a small persistent offset (the sum's dof grow with the window, the mean's
  do not); a localisation bias is such an offset too (docs/attacks.md). The reported
  pose is the aligned observation's ``collab_reported_poses``; ``bias_t`` / ``bias_r``
  (the persistent part of the noise) widen the mean's allowance. A step whose q alone
  has a p-value below ``strong`` fails at once, however quiet the window (a drift that
  has just grown large).
* **Consistency after alignment**: every pair of sources (the ego and its collaborators,
  all in the ego frame) is compared box by box: a box matches the other source's nearest
  box within ``match_m`` m; it conflicts with it when their footprints overlap without
  matching (two cars cannot overlap); it is unconfirmed when the other source has
  nothing there although the box lies in its clear view (closer than ``view_m`` m to its
  origin, no other box's centre within ``occlusion_m`` m of the sight line). A
  collaborator's counts against the ego and every other collaborator, summed over the
  last ``window`` steps, are tested against the shares an honest one shows
  (``conflict_rate``, ``miss_rate``; one-sided binomial tests, Bonferroni over the
  consistency tests).
  It fails when the window's counts are significant at ``alpha`` and this step's alone
  have a p-value of at most ``recent`` (0.5): a disagreement the aligner has since
  resolved, an honest collaborator misaligned on one step, no longer counts. Evidence
  of boxes nobody has holds, though: where the window's lone unconfirmed boxes (no box
  of the judge within ``orphan_m``) alone have a p-value below ``sticky`` (1e-3), in
  this test and the relative test below (the orphan test: its window), the collaborator
  fails whatever this step says, until clean steps dilute its window (conflicts and
  missed claims never hold, nor boxes a judge places a little off: an honest
  collaborator the aligner leaves a metre or two off shows many). A box within
  ``own_car_m`` (2.5 m) of a vehicle source's origin (id starting with ``car_prefix``)
  is its own car, which it does not detect: never unconfirmed by it.
* **Claimed position**: a vehicle collaborator's (id starting with ``car_prefix``; an RSU
  has no car) aligned pose puts its own car at a place in the ego frame; every other
  vehicle source (the ego included when it is one; an RSU: below) with that place
  in its clear view should have a box within ``claim_m`` m of it. Each such (claim,
  witness) is a trial of the pair's evidence, its misses tested against
  ``claim_miss_rate`` (one-sided binomial, a third test of the same Bonferroni,
  window and ``recent`` rule). Forged boxes cannot move the liar's real car: a spoofed
  pose the aligner keeps leaves its claimed place empty. A claim's clear view reaches
  ``claim_view_m`` (the rate allows for the misses of far witnesses). With
  ``use_rsu_witness`` an RSU (id starting with ``rsu_prefix``; ego or collaborator)
  witnesses too, beyond ``rsu_blind_m`` (the foot of its mast, below its LiDAR's lowest
  beam), and only boxes at least ``rsu_over_m`` tall (trucks, buses) block its view: from
  its mast it sees a car's roof over the cars. The claimant's own boxes never shade its
  claimed place (a liar could report one in the witness's line of sight).
* **Relative share of unconfirmed boxes**: a collaborator's boxes unconfirmed by the ego
  and the others, over the window, against ``relative_margin`` times the pooled share of
  the other collaborators' boxes (judged by all but it): a one-sided Wald z-test, a
  fourth test of the same Bonferroni, window and ``recent`` rule, judged against every
  collaborator (outside the consensus). It has power where a fixed ``miss_rate`` must
  sit above every honest share (a few ghosts).
* **Orphan boxes**: a collaborator's box is an orphan when a judge (the ego, or a
  collaborator no other test rejects this step) has it in clear view and leaves it
  unconfirmed, and no judge has a box within ``orphan_m`` m of it (so a collaborator the
  aligner left a metre or two off, whose boxes sit beside the others', shows none); only
  boxes scored at least ``orphan_score`` count (a detector's clutter scores low). Its
  orphans over the window are tested against the share ``orphan_rate`` (one-sided
  binomial, a fifth test of the same Bonferroni, window and ``recent`` rule), judged
  against every collaborator. Honest misses are matched by another source; a ghost in
  clear view is matched by none. A *witnessed* orphan is one that ``witness_judges`` (2)
  judges or more have in clear view and leave unconfirmed: rarer still for an honest
  box (about 0.02 % of them behind roco at noise 0.4), so two of them are evidence on a
  first step; they are tested against ``witnessed_rate`` (0.0005) beside the orphans
  (``use_witnessed``): the orphan test spends ``witnessed_level`` (a quarter) of its level
  on them and the rest on all orphans (a weighted Bonferroni inside the test: p-values
  divided by 0.25 and 0.75, the smaller counts; same window and rules, the other tests'
  Bonferroni unchanged).
* **Consensus** (ROBOSAC-style): the largest set of collaborators each of which passes
  that test against the ego and the others *of the set* is kept (every subset is tried,
  largest first: at most 2^N of them; ties go to the set whose members agree best); the
  others are rejected. Without it a liar's disagreement also weighs on the honest
  collaborators it disagrees with.
* **Re-test under another pose** (``use_repose``): before the consistency test rejects a
  collaborator, it is judged again under poses that do not trust the base aligner's fit
  (:func:`roco_env.policies.defend_refit.alternative_poses`: a re-fit of its boxes alone
  against the ego's and the kept collaborators', then its reported pose); it is kept
  where its window is no longer significant and every kept collaborator still passes.
  An honest collaborator the aligner left misaligned agrees again; a liar's forged,
  ghost or withheld boxes do not.

The ego's own boxes are trusted. State (the windows) is kept per ego and collaborator id
(``info["agent"]``, ``info["collaborators"]``); :meth:`Defend.reset` forgets it.
"""

from __future__ import annotations

import itertools
from collections import deque
from collections.abc import Callable, Hashable, Mapping
from dataclasses import dataclass, replace
from typing import Any, NamedTuple

import numpy as np
from scipy.special import bdtrc, chdtrc, ndtr

from roco_env.geometry import bev_iou_pairs, se2_compose, se2_inverse, wrap_angle
from roco_env.policies.adapter import collaborator_keys
from roco_env.policies.base import check_aligner_base
from roco_env.policies.defend_refit import alternative_poses
from roco_env.policies.landmarks import params_from_kwargs
from roco_env.schema import spec

__all__ = ["BoxStatus", "Defend", "DefendParams", "PairEvidence", "box_status", "centre_distances",
           "claim_evidence", "clear_view", "pair_evidence"]

EGO = "__ego__"  # the ego's key among the sources
_SHIFT, _TURN, _DISTANCE = 4, 5, 6  # columns of the aligned observation's diagnostics
_OCCLUDER = [0, 1, 5]  # a box's columns that shade a view: centre x, y and height (m)


@dataclass(frozen=True)
class PairEvidence:
    """What one source's boxes say about another's: counts of boxes that match, conflict
    (overlap without matching) or are unconfirmed (in the other's clear view, nothing
    there); and of claimed places (a vehicle collaborator's car where its pose puts it) in
    the other's clear view, and of those where the other sees no car; ``lone``: the
    unconfirmed boxes with no box of the other within a given distance (a box the other
    has nowhere near, not one it places a little off)."""

    matches: int
    conflicts: int
    unconfirmed: int
    claims: int = 0
    claims_missed: int = 0
    lone: int = 0

    def __add__(self, other: PairEvidence) -> PairEvidence:
        return PairEvidence(self.matches + other.matches, self.conflicts + other.conflicts,
                            self.unconfirmed + other.unconfirmed, self.claims + other.claims,
                            self.claims_missed + other.claims_missed, self.lone + other.lone)


NO_EVIDENCE = PairEvidence(0, 0, 0)


def clear_view(origin: np.ndarray, targets: np.ndarray, occluders: np.ndarray,
               reach: float, radius: float, own: float, blind: float = 0.0) -> np.ndarray:
    """(k,) bool: whether each target point (k, 2) lies within ``reach`` m of ``origin``
    (2,), and not within ``blind`` m (the viewer's own car, which it does not detect), with
    no occluder centre (M, 2) within ``radius`` m of the sight line between them; occluders
    within ``own`` m of the target (its own box), or within ``max(own, blind)`` m of the
    origin (the viewer's car), block nothing. Metres, one frame."""
    ray = targets - origin
    length2 = np.maximum(np.sum(ray**2, axis=1), 1e-12)
    near = (np.sqrt(length2) < reach) & (np.sqrt(length2) >= blind)
    seen = np.zeros(targets.shape[0], dtype=bool)
    if not near.any():
        return seen
    rel = occluders - origin
    close = np.hypot(*rel.T) < reach + radius  # no farther occluder is near a sight line
    rel, occluders = rel[close], occluders[close]
    ray, length2, targets = ray[near], length2[near], targets[near]
    along = (ray @ rel.T) / length2[:, None]  # (k, M): position on the sight line, 0..1
    across = np.hypot(rel[None, :, 0] - along * ray[:, None, 0],
                      rel[None, :, 1] - along * ray[:, None, 1])
    own_box = np.hypot(*(occluders[None, :, :] - targets[:, None, :]).transpose(2, 0, 1)) < own
    viewer = np.hypot(*rel.T) < max(own, blind)
    blocked = (along > 0.0) & (along < 1.0) & (across < radius) & ~own_box & ~viewer[None, :]
    seen[near] = ~blocked.any(axis=1)
    return seen


def centre_distances(boxes: np.ndarray, other: np.ndarray) -> np.ndarray:
    """(k, M) BEV distances (m) between the centres of ``boxes`` (k, 7) and ``other``
    (M, 7), one frame; the other way round is its transpose."""
    return np.hypot(boxes[:, None, 0] - other[None, :, 0], boxes[:, None, 1] - other[None, :, 1])


class BoxStatus(NamedTuple):
    """Per box (k,) of one source as another source's boxes judge it: ``matched`` (its
    nearest box within ``match_m``), ``conflict`` (overlapping without matching),
    ``unconfirmed`` (neither, in the other's clear view) and ``gap`` (m, the distance to
    the nearest box's centre; inf where the other has none)."""

    matched: np.ndarray
    conflict: np.ndarray
    unconfirmed: np.ndarray
    gap: np.ndarray

    def evidence(self, lone_m: float | None = None) -> PairEvidence:
        """The counts of :class:`PairEvidence`; ``lone`` those of the unconfirmed boxes
        whose ``gap`` exceeds ``lone_m`` (m; None: not counted, 0)."""
        lone = 0 if lone_m is None else int(np.sum(self.unconfirmed & (self.gap > lone_m)))
        return PairEvidence(int(self.matched.sum()), int(self.conflict.sum()),
                            int(self.unconfirmed.sum()), lone=lone)


def box_status(boxes: np.ndarray, other: np.ndarray, other_origin: np.ndarray,
               occluders: np.ndarray, match_m: float, view_m: float,
               occlusion_m: float, distance: np.ndarray | None = None,
               blind_m: float = 0.0) -> BoxStatus:
    """How the boxes of source ``other`` (M, 7) at ``other_origin`` (2,) judge each of
    ``boxes`` (k, 7) (one frame); ``occluders`` (all sources' box centres) shade its view;
    ``distance``: their :func:`centre_distances`, when already computed; a box within
    ``blind_m`` of ``other_origin`` (the other's own car) is never unconfirmed."""
    none, far = np.zeros(boxes.shape[0], dtype=bool), np.full(boxes.shape[0], np.inf)
    if boxes.shape[0] == 0:
        return BoxStatus(none, none, none, far)
    if other.shape[0] == 0:
        seen = clear_view(other_origin, boxes[:, :2], occluders, view_m, occlusion_m, match_m,
                          blind_m)
        return BoxStatus(none, none, seen, far)
    if distance is None:
        distance = centre_distances(boxes, other)
    nearest = np.argmin(distance, axis=1)
    gap = distance[np.arange(boxes.shape[0]), nearest]
    matched = gap < match_m
    # only an unmatched box can conflict, and only with a box its circumscribed circle meets
    radii = np.hypot(boxes[:, 3], boxes[:, 4]) + np.hypot(other[nearest, 3], other[nearest, 4])
    close = ~matched & (gap < radii / 2)
    overlap = np.zeros_like(matched)
    if close.any():
        overlap[close] = bev_iou_pairs(boxes[close], other[nearest[close]]) > 0.0
    loose = ~matched & ~overlap
    seen = np.zeros_like(loose)
    if loose.any():
        seen[loose] = clear_view(other_origin, boxes[loose, :2], occluders, view_m, occlusion_m,
                                 match_m, blind_m)
    return BoxStatus(matched, ~matched & overlap, seen, gap)


def pair_evidence(boxes: np.ndarray, other: np.ndarray, other_origin: np.ndarray,
                  occluders: np.ndarray, match_m: float, view_m: float,
                  occlusion_m: float, distance: np.ndarray | None = None) -> PairEvidence:
    """What the boxes of source ``other`` (M, 7) at ``other_origin`` (2,) say about
    ``boxes`` (k, 7): the counts of :func:`box_status` (same arguments)."""
    return box_status(boxes, other, other_origin, occluders, match_m, view_m, occlusion_m,
                      distance).evidence()


def claim_evidence(claimed: np.ndarray, witness: np.ndarray, witness_origin: np.ndarray,
                   occluders: np.ndarray, claim_m: float, view_m: float,
                   occlusion_m: float, blind_m: float = 0.0) -> PairEvidence:
    """What a witness's boxes ``witness`` (M, 7), seen from ``witness_origin`` (2,), say
    about the place ``claimed`` (2,) where a vehicle collaborator's pose puts its own car
    (one frame, metres): nothing when the place is out of the witness's clear view (or
    within ``blind_m`` of its origin, where its sensor sees no car), else one claim,
    missed when no witness box centre lies within ``claim_m`` of it."""
    if not clear_view(witness_origin, claimed[None, :], occluders, view_m, occlusion_m,
                      claim_m, blind_m)[0]:
        return NO_EVIDENCE
    there = witness.shape[0] > 0 and bool(
        np.min(np.hypot(*(witness[:, :2] - claimed).T)) < claim_m)
    return PairEvidence(0, 0, 0, 1, int(not there))


def _positive(default: float, doc: str) -> Any:
    return spec(default, low=0.0, low_open=True, doc=doc)


def _open_share(default: float, doc: str) -> Any:
    return spec(default, low=0.0, high=1.0, low_open=True, high_open=True, doc=doc)


@dataclass(frozen=True)
class DefendParams:
    """``defend``'s parameters (module docstring)."""

    base: str = spec("roco", doc="the aligner's policy spec the env runs (action.base)")
    sigma_t: float = _positive(0.4, "localisation noise assumed per agent and axis, m (std)")
    sigma_r: float = _positive(0.4, "localisation noise assumed on the heading, deg (std)")
    bias_t: float = spec(0.0, low=0.0, doc="the part of the localisation noise that "
                         "persists over an episode, m per agent and axis (std; 0: the noise "
                         "is independent from step to step)")
    bias_r: float = spec(0.0, low=0.0, doc="the same on the heading, deg (std)")
    alpha: float = _open_share(0.01, "level of every test")
    window: int = spec(10, low=1, doc="steps of history per collaborator and pair")
    match_m: float = _positive(1.0, "two sources' boxes closer than this are one object, m")
    view_m: float = _positive(40.0, "a source surely detects a car in its clear view this "
                              "near, m")
    occlusion_m: float = _positive(1.5, "a box centre this near a sight line blocks it, m")
    own_car_m: float = spec(2.5, low=0.0, doc="a box this near a source's origin (m) is its "
                            "own car, which it does not detect: never unconfirmed by it (0: "
                            "counted like any other box)")
    miss_rate: float = _open_share(0.09, "share of unconfirmed boxes an honest collaborator "
                                   "shows")
    conflict_rate: float = _open_share(0.03, "share of conflicting boxes an honest "
                                       "collaborator shows")
    recent: float = spec(0.5, low=0.0, high=1.0, doc="a collaborator failing the test over "
                         "the window is kept when this step's evidence alone has a p-value "
                         "above this (1: the window decides alone)")
    strong: float = spec(0.001, low=0.0, high=1.0, doc="a correction whose own p-value "
                         "(this step alone) is below this fails at once, however quiet "
                         "the window (0: the window decides alone)")
    sticky: float = spec(1e-3, low=0.0, high=1.0, doc="where the window's evidence of "
                         "boxes nobody has (unconfirmed with no box of the judge within "
                         "orphan_m: the unconfirmed test's, the relative test's; the orphan "
                         "test's window) has a p-value (Bonferroni included) below this, the "
                         "test fails whatever this step's evidence says (the recent rule is "
                         "waived until the evidence leaves the window; conflicts and missed "
                         "claims never hold; 0: never waived)")
    use_correction: bool = spec(True, doc="the correction (temporal) tests")
    use_offset: bool = spec(True, doc="the mean-offset test among the correction tests "
                            "(off: the sum of q alone, at level alpha)")
    use_consistency: bool = spec(True, doc="the consistency test after alignment")
    use_consensus: bool = spec(True, doc="the consensus over subsets of collaborators")
    use_claim: bool = spec(True, doc="the claimed-position test of vehicle collaborators")
    use_relative: bool = spec(True, doc="the relative test of a collaborator's unconfirmed "
                              "share against the other collaborators' (a consistency test: "
                              "runs only with use_consistency)")
    use_orphan: bool = spec(True, doc="the test of orphan boxes: unconfirmed by a judge with "
                            "them in clear view and matched by none (a consistency test: "
                            "runs only with use_consistency)")
    orphan_m: float = _positive(2.0, "a box with a judge's box (the ego's, or a collaborator's "
                                "no other test rejects) this near (m) is no orphan (a "
                                "misaligned collaborator's boxes lie near the others')")
    orphan_score: float = spec(0.5, low=0.0, high=1.0, doc="only boxes scored this or "
                               "higher count in the orphan test (the realistic detector's "
                               "false positives score at most 0.45)")
    orphan_rate: float = _open_share(0.015, "share of an honest collaborator's boxes that are "
                                     "orphans (unconfirmed by a source with them in clear "
                                     "view, matched by none)")
    use_witnessed: bool = spec(True, doc="the test of witnessed orphans: orphans left "
                               "unconfirmed by witness_judges judges or more (a consistency "
                               "test: runs only with use_consistency and use_orphan)")
    witness_judges: int = spec(2, low=2, doc="an orphan this many judges have in clear view "
                               "and leave unconfirmed is a witnessed orphan")
    witnessed_rate: float = _open_share(0.0005, "share of an honest collaborator's boxes that "
                                        "are witnessed orphans")
    witnessed_level: float = _open_share(0.25, "share of the orphan test's level spent on "
                                         "the witnessed orphans (the rest on all orphans)")
    relative_margin: float = spec(1.2, low=1.0, doc="the relative test rejects a share of "
                                  "unconfirmed boxes above this many times the others'")
    claim_m: float = _positive(2.0, "a witness box this near a claimed place is the car, m")
    claim_view_m: float = _positive(50.0, "a witness's clear view of a claimed place reaches "
                                    "this far (m): a car seen in at least 1 - claim_miss_rate "
                                    "of cases")
    claim_miss_rate: float = _open_share(0.1, "share of claimed places in a witness's "
                                         "clear view where an honest vehicle's car is not "
                                         "seen")
    use_rsu_witness: bool = spec(True, doc="RSUs (ids starting with rsu_prefix; the ego or "
                                 "a collaborator) witness the claimed places of vehicles "
                                 "beyond rsu_blind_m (off: only vehicles witness)")
    rsu_prefix: str = spec("rsu_", doc="agent ids of RSUs start so (a source neither a "
                           "vehicle nor an RSU witnesses no claim)")
    rsu_blind_m: float = spec(8.0, low=0.0, doc="no claimed place within this of an RSU is "
                              "witnessed by it (m): its mast-mounted LiDAR sees no car at the "
                              "mast's foot (at the scenes' rsu_height 5.5 m and lowest beam "
                              "24.8 deg down a car's roof enters the beam at about 8.7 m; "
                              "in the replays RSUs saw honest cars 8-12 m away in 228 of "
                              "228 cases, 6-8 m in 135 of 155). Set it for other mast "
                              "heights")
    rsu_over_m: float = _positive(2.5, "an RSU's LiDAR, on its mast, sees a car's roof over "
                                  "boxes lower than this (m): only taller ones (trucks, "
                                  "buses) block its view of a claimed place")
    use_repose: bool = spec(True, doc="before the consistency test rejects a collaborator, "
                            "re-test it under its reported pose and a re-fit of its boxes "
                            "against the ego's and the kept collaborators' (an honest one the "
                            "aligner left misaligned agrees again; a liar does not): kept "
                            "when one passes")
    refit_m: float = _positive(3.0, "the re-fit of use_repose pairs each box with the nearest "
                               "target box within this (m), then within half of it")
    car_prefix: str = spec("cav_", doc="agent ids of vehicles start so (the others, RSUs, "
                           "have no car to see)")

    def __post_init__(self) -> None:
        check_aligner_base("defend", self.base)
        if self.use_rsu_witness and self.rsu_blind_m >= self.claim_view_m:
            raise ValueError(f"defend: rsu_blind_m ({self.rsu_blind_m}) must be below "
                             f"claim_view_m ({self.claim_view_m}) with use_rsu_witness: an "
                             "RSU would witness no claim (set use_rsu_witness=False)")


class Defend:
    """``Defend(base="roco", **params)(obs, info) -> (N,) int64`` gate action (1 = reject),
    params the fields of :class:`DefendParams`. Measured on clean episodes, the shares of
    unconfirmed and conflicting boxes an honest collaborator shows behind roco at noise 0.4
    are about 0.04 (its own car left out, ``own_car_m``; up to 0.11 for one collaborator)
    and 0.016, of its claimed places a witness sees empty 0.044-0.055 with RSU witnesses
    and claims to 50 m (0.02-0.05 by vehicles within 40 m; docs/attacks.md)."""

    keeps_state = "per ego and collaborator (info['agent'], info['collaborators'])"
    last_result = None  # it reports no alignment of its own: the env's base aligner aligns

    def __init__(self, **params: Any) -> None:
        p = self.params = params_from_kwargs(DefendParams, params, "defend")
        self.env_overrides = {"action.mode": "gate", "action.base": p.base,
                              "observation.mode": "aligned"}
        self.sigma_r = np.radians(p.sigma_r)
        self.bias_r = np.radians(p.bias_r)
        self._geometry = (p.match_m, p.view_m, p.occlusion_m)  # pair_evidence's thresholds
        self._claim = (p.claim_m, p.claim_view_m, p.occlusion_m)  # claim_evidence's
        self.use = {"correction": p.use_correction, "consistency": p.use_consistency,
                    "consensus": p.use_consensus, "claim": p.use_claim,
                    "relative": p.use_relative, "orphan": p.use_orphan}
        # the consistency tests' Bonferroni
        self._tests = 2 + p.use_claim + p.use_relative + p.use_orphan
        # per key, each step: (q,), or with the mean test (q, z, b): the whitened offset z
        # and bias std b, (3,) each
        self._q: dict[Hashable, deque] = {}
        self._pairs: dict[Hashable, deque] = {}
        # per key, each step: (orphans, boxes, witnessed orphans)
        self._orphans: dict[Hashable, deque] = {}
        self.last_reasons: tuple[str, ...] = ()
        self.last_pairs: dict[tuple, PairEvidence] = {}  # (judged, judge) -> window's
        self.last_now: dict[tuple, PairEvidence] = {}  # (judged, judge) -> this step's
        self._status: dict[tuple, BoxStatus] = {}  # (judged, judge) -> this step's per box
        # slot -> (orphans, boxes) over the window and this step's
        self.last_orphans: dict[int, tuple[tuple[int, int], tuple[int, int]]] = {}
        # slot -> witnessed orphans over the window and this step's
        self.last_witnessed: dict[int, tuple[int, int]] = {}
        # slot -> the alternative pose (3,) under which use_repose kept it, this step
        self.last_reposed: dict[int, np.ndarray] = {}

    def reset(self) -> None:
        """Forget every collaborator's and pair's history (call between episodes)."""
        self._q.clear()
        self._pairs.clear()
        self._orphans.clear()

    def __call__(self, observation: Mapping[str, Any], info: Mapping | None = None
                 ) -> np.ndarray:
        mask = np.asarray(observation["collab_mask"]) > 0
        filled = np.flatnonzero(mask)
        keys = collaborator_keys(dict(info or {}), filled, "defend")
        reasons = [""] * mask.shape[0]
        if self.use["correction"]:
            diagnostics = np.asarray(observation["diagnostics"])
            offsets = _offsets(observation, filled) if self.params.use_offset else None
            for index, (slot, key) in enumerate(zip(filled, keys, strict=True)):
                offset = None if offsets is None else offsets[index]
                if self._implausible(key, diagnostics[slot], offset):
                    reasons[slot] = "correction"
        if self.use["consistency"] and filled.size:
            kept = self._consensus(observation, filled, [key[1] for key in keys],
                                   keys[0][0] if keys else None)
            for slot in filled:
                if slot not in kept and not reasons[slot]:
                    reasons[slot] = "consistency"
            if self.use["relative"]:
                for slot in self.relatively_unconfirmed([int(s) for s in filled]):
                    reasons[slot] = reasons[slot] or "relative"
            if self.use["orphan"]:  # judged by the ego and the collaborators kept so far
                judges = [EGO, *(int(s) for s in filled if not reasons[s])]
                scores = np.asarray(observation["collab_scores"], dtype=float)
                masks = np.asarray(observation["collab_box_mask"]) > 0
                scored = [scores[s][masks[s]] >= self.params.orphan_score for s in filled]
                for slot in self.orphaned([int(s) for s in filled], judges,
                                          keys[0][0] if keys else None,
                                          [key[1] for key in keys], scored):
                    reasons[slot] = reasons[slot] or "orphan"
        self.last_reasons = tuple(reasons)
        return np.array([1 if reason else 0 for reason in reasons], dtype=np.int64)

    def _spread(self, distance: float) -> tuple[float, float]:
        """The variances (m^2, rad^2) of an honest correction's shift and turn for a
        collaborator ``distance`` m away: ``s_t^2``, ``s_r^2`` of the module docstring."""
        return (2.0 * self.params.sigma_t**2 + 2.0 * (distance * self.sigma_r) ** 2,
                2.0 * self.sigma_r**2)

    def _plausible(self, pose: np.ndarray, reported: np.ndarray) -> bool:
        """Whether ``pose`` (3,) is a correction of ``reported`` (3,) (m, m, rad, ego
        frame) the assumed noise explains: its q (module docstring) has a p-value of at
        least ``alpha`` (a re-fit that moves a spoofer back to its true pose is not)."""
        s_t2, s_r2 = self._spread(float(np.hypot(*reported[:2])))
        turn = float(wrap_angle(pose[2] - reported[2]))
        q = float(np.sum((pose[:2] - reported[:2]) ** 2)) / s_t2 + turn**2 / s_r2
        return bool(chdtrc(3, q) >= self.params.alpha)

    def _implausible(self, key: Hashable, diagnostics: np.ndarray,
                     offset: np.ndarray | None) -> bool:
        """Record this step's correction statistic q of ``key`` and its whitened signed
        correction ``offset`` (3,) (m, m, rad in the collaborator's reported frame; None:
        the mean test is off); whether the window fails the sum test or the mean test
        (each at alpha / 2 when both run), or this step's q alone fails at ``strong``."""
        distance = float(diagnostics[_DISTANCE])
        s_t2, s_r2 = self._spread(distance)
        q = float(diagnostics[_SHIFT]) ** 2 / s_t2 + np.radians(float(diagnostics[_TURN])) ** 2 \
            / s_r2
        step: tuple = (q,)
        if offset is not None:  # (q, whitened offset, whitened bias std), each (3,)
            spread = np.sqrt([s_t2, s_t2, s_r2])
            bias = np.sqrt([2.0 * self.params.bias_t**2 + 2.0 * (distance * self.bias_r) ** 2]
                           * 2 + [2.0 * self.bias_r**2])
            step = (q, offset / spread, bias / spread)
        history = self._q.setdefault(key, deque(maxlen=self.params.window))
        history.append(step)
        steps = len(history)
        level = self.params.alpha / (1 if offset is None else 2)
        if chdtrc(3 * steps, sum(entry[0] for entry in history)) < level \
                or chdtrc(3, q) < self.params.strong:
            return True
        if offset is None:
            return False
        # sum of z per axis: variance steps (the noise) + (sum of bias / spread)^2 (a bias
        # shared by every step); use_offset is fixed, so every entry holds both
        total = sum(entry[1] for entry in history)
        shared = sum(entry[2] for entry in history)
        return bool(chdtrc(3, float(np.sum(total**2 / (steps + shared**2)))) < level)

    def _consensus(self, observation: Mapping[str, Any], filled: np.ndarray,
                   names: list[str], ego: Hashable) -> set[int]:
        """The filled slots kept by the consistency test (and the consensus, when on)."""
        sources = _sources(observation, filled)
        occluders = _shades(sources)
        ids = {EGO: EGO, **{slot: name for slot, name in zip(filled, names, strict=True)}}

        def starting(prefix: str) -> set:
            return {key for key, name in ids.items()
                    if str(ego if key == EGO else name).startswith(prefix)}
        # vehicles have a car of their own, which they do not detect; they claim a place
        # and witness others' claims; RSUs witness them too with use_rsu_witness
        vehicles = starting(self.params.car_prefix)
        cars = vehicles if self.use["claim"] else set()
        rsus = starting(self.params.rsu_prefix) if self.params.use_rsu_witness else set()
        blind = {key: self.params.own_car_m if key in vehicles else 0.0 for key in ids}
        self.last_pairs, self.last_now, self._status = {}, {}, {}
        for a, b in itertools.combinations(sources, 2):
            for (judged, judge), (evidence, status) in self._judge(
                    a, b, sources, occluders, (cars, rsus), blind).items():
                history = self._pairs.setdefault((ego, ids[judged], ids[judge]),
                                                 deque(maxlen=self.params.window))
                history.append(evidence)
                self._status[judged, judge] = status
                self.last_pairs[judged, judge] = sum(history, NO_EVIDENCE)
                self.last_now[judged, judge] = evidence
        kept = self.kept([int(s) for s in filled])
        self.last_reposed = {}
        if self.params.use_repose:
            self._repose(observation, filled, sources, kept, (ego, ids, (cars, rsus), blind))
        return kept

    def _judge(self, a: Hashable, b: Hashable, sources: Mapping, occluders: Shades,
               witnesses: tuple[set, set], blind: Mapping
               ) -> dict[tuple, tuple[PairEvidence, BoxStatus]]:
        """This step's evidence and per-box status of the pair of sources ``a``, ``b``
        (keys of ``sources``: (boxes, origin), ego frame), both ways: (judged, judge) ->
        (what the judge's boxes say about the judged's boxes, and about its claimed place
        when the judged is a vehicle (``witnesses`` = (vehicle keys with claims on, RSU
        keys with use_rsu_witness)) and no ego and the judge a vehicle or an RSU; the
        :func:`box_status`). ``occluders``: every source's boxes as :class:`Shades`."""
        (boxes_a, origin_a), (boxes_b, origin_b) = sources[a], sources[b]
        cars, rsus = witnesses
        every = occluders.boxes[:, :2]
        distance = centre_distances(boxes_a, boxes_b)
        status = {(a, b): box_status(boxes_a, boxes_b, origin_b, every, *self._geometry,
                                     distance, blind[b]),
                  (b, a): box_status(boxes_b, boxes_a, origin_a, every, *self._geometry,
                                     distance.T, blind[a])}
        judged = {}
        for (one, other), seen in status.items():
            evidence = seen.evidence(self.params.orphan_m)
            if one in cars and one != EGO and (other in cars or other in rsus):
                # the claimant's own boxes do not shade its claimed place (a liar could
                # report one in the line of sight); an RSU's LiDAR looks down over the
                # cars: only boxes as tall as rsu_over_m block its view of a car's roof
                # (and it sees no car at its own mast's foot)
                shade = occluders.without(one)
                if other in rsus:
                    shade = shade[shade[:, 2] >= self.params.rsu_over_m]
                evidence += claim_evidence(sources[one][1], sources[other][0],
                                           sources[other][1], shade[:, :2], *self._claim,
                                           self.params.rsu_blind_m if other in rsus else 0.0)
            judged[one, other] = (evidence, seen)
        return judged

    def _repose(self, observation: Mapping[str, Any], filled: np.ndarray, sources: dict,
                kept: set[int], context: tuple) -> None:
        """Re-test each filled slot ``kept`` lacks under the alternative poses of
        :func:`alternative_poses` (its reported pose, a re-fit against the ego's and the
        kept collaborators' boxes) that the assumed noise explains as a correction of
        its reported pose (:meth:`_plausible`), this step's evidence of every pair it is in judged
        again under that pose (the window's earlier steps as they were): the first pose
        under which its window is not significant (no ``recent`` rule: a liar whose
        evidence has built up, an eraser's withheld boxes, is not released by one quiet
        step) and every kept collaborator passes the consistency test keeps it
        (added to ``kept``; its evidence and statuses replaced by that pose's, for the
        relative and orphan tests; the pose in :attr:`last_reposed`). ``context``: (ego
        id, key -> id, (vehicle keys, RSU keys) as :meth:`_judge` takes them, key -> blind
        radius)."""
        ego, ids, witnesses, blind = context
        if "collab_reported_poses" not in observation:
            raise ValueError("defend's use_repose re-fits from observation["
                             "'collab_reported_poses'] (the aligned observation's reported "
                             "relative poses); give it, or use_repose=False")
        aligned = np.asarray(observation["collab_rel_poses"], dtype=float)
        reported = np.asarray(observation["collab_reported_poses"], dtype=float)
        gates = (self.params.refit_m, self.params.refit_m / 2.0)
        for slot in (int(s) for s in filled if int(s) not in kept):
            targets = np.concatenate([sources[key][0][:, :2] for key in (EGO, *sorted(kept))])
            for pose, boxes in alternative_poses(sources[slot][0], aligned[slot],
                                                 reported[slot], targets, gates):
                if not self._plausible(pose, reported[slot]):
                    continue
                trial = {**sources, slot: (boxes, pose[:2])}
                occluders = _shades(trial)
                judged = {}
                for other in trial:
                    if other != slot:
                        judged.update(self._judge(slot, other, trial, occluders, witnesses,
                                                  blind))
                saved = {key: (self.last_pairs[key], self.last_now[key]) for key in judged}
                histories = {key: self._pairs[ego, ids[key[0]], ids[key[1]]] for key in judged}
                for key, (evidence, _) in judged.items():
                    self.last_pairs[key] = sum(list(histories[key])[:-1], evidence)
                    self.last_now[key] = evidence
                group = sorted(kept | {slot})
                if self._p_value(slot, group, self.last_pairs) >= self.params.alpha \
                        and all(self._consistent(member, group) for member in group):
                    for key, (evidence, status) in judged.items():
                        histories[key][-1] = evidence
                        self._status[key] = status
                    kept.add(slot)
                    sources[slot] = trial[slot]
                    self.last_reposed[slot] = pose
                    break
                for key, (window, now) in saved.items():
                    self.last_pairs[key], self.last_now[key] = window, now

    def kept(self, slots: list[int]) -> set[int]:
        """The slots the consistency test (and the consensus, when on) keeps, judged on
        :attr:`last_pairs` (each pair's evidence over the window) and :attr:`last_now`
        (this step's)."""
        if not self.use["consensus"]:
            return {slot for slot in slots if self._consistent(slot, slots)}
        for size in range(len(slots), -1, -1):
            fits = [chosen for chosen in itertools.combinations(slots, size)
                    if all(self._consistent(slot, chosen) for slot in chosen)]
            if fits:  # ties: the set whose members agree best (sum of log p-values)
                return set(max(fits, key=lambda chosen: sum(
                    np.log(max(self._p_value(slot, chosen, self.last_pairs), 1e-300))
                    for slot in chosen)))
        return set()

    def _consistent(self, slot: int, group: tuple[int, ...] | list[int]) -> bool:
        """Whether ``slot`` passes the test against ``group``: its disagreements over the
        window are not significant at alpha, or this step's alone have a p-value above
        ``recent`` (a past disagreement since resolved, an early misalignment the aligner
        has corrected, no longer counts) and its lone unconfirmed boxes (no box of the
        judge within ``orphan_m``) over the window alone are not below ``sticky``
        (conflicts never hold, nor boxes a judge places a little off: a misaligned honest
        collaborator shows many, and the aligner may correct it)."""
        return not self._fails(
            self._p_value(slot, group, self.last_pairs),
            lambda: self._p_value(slot, group, self.last_now),
            lambda: self._p_value(slot, group, self.last_pairs, lone_only=True))

    def _fails(self, window: float, now: Callable[[], float],
               held: Callable[[], float] | None = None) -> bool:
        """A consistency test's verdict from its window p-value (Bonferroni included) and
        ``now()``, this step's alone: significant at alpha and this step's p-value at most
        ``recent``, or the window's (``held()``: the part of it that may hold) below
        ``sticky`` whatever this step says."""
        if window >= self.params.alpha:
            return False
        return (window if held is None else held()) < self.params.sticky \
            or now() <= self.params.recent

    def _p_value(self, slot: int, group: tuple[int, ...] | list[int],
                 pairs: dict[tuple, PairEvidence], lone_only: bool = False) -> float:
        """How likely an honest collaborator shows the conflicts, unconfirmed boxes or
        missed claims that ``slot`` shows against the ego and the other collaborators of
        ``group`` in ``pairs`` (directed: (judged, judge) -> evidence): the smallest
        p-value of the one-sided binomial tests times the number of consistency tests
        (Bonferroni: conflicts and unconfirmed boxes, missed claims with the claim test, the
        relative test of :meth:`relatively_unconfirmed` and the orphan test of
        :meth:`orphaned` when on; 1 without evidence); ``lone_only``: the test of the lone
        unconfirmed boxes alone (:class:`PairEvidence`; same Bonferroni)."""
        others = [other for other in (EGO, *group) if other != slot]
        evidence = sum((pairs[slot, other] + pairs[other, slot] for other in others),
                       NO_EVIDENCE)
        total = evidence.matches + evidence.conflicts + evidence.unconfirmed
        unconfirmed = evidence.lone if lone_only else evidence.unconfirmed
        tails = [bdtrc(unconfirmed - 1, total, self.params.miss_rate)] if total else []
        if total and not lone_only:
            tails.append(bdtrc(evidence.conflicts - 1, total, self.params.conflict_rate))
        if evidence.claims and not lone_only:
            tails.append(bdtrc(evidence.claims_missed - 1, evidence.claims,
                               self.params.claim_miss_rate))
        return float(min(1.0, self._tests * min(tails))) if tails else 1.0

    def relatively_unconfirmed(self, slots: list[int]) -> set[int]:
        """The slots whose share of unconfirmed boxes, as the ego and every other
        collaborator judge them, exceeds ``relative_margin`` times the pooled share of the
        other collaborators' boxes (judged by all but it) significantly over the window
        (level alpha over the consistency tests' Bonferroni) and this step's alone have a
        p-value of at most ``recent`` (or the same test of the lone unconfirmed boxes over
        the window, :class:`PairEvidence`, is below ``sticky``). Judged against every
        collaborator, not a consensus set's: a liar's boxes lie in its pool, a smaller
        pool's share is noisier."""
        def tail(slot: int, pairs: dict[tuple, PairEvidence], lone: bool = False) -> float:
            judges = [EGO, *(other for other in slots if other != slot)]
            own = sum((pairs[slot, judge] for judge in judges), NO_EVIDENCE)
            rest = sum((pairs[member, judge] for member in judges[1:] for judge in judges
                        if judge != member), NO_EVIDENCE)
            if lone:
                own, rest = replace(own, unconfirmed=own.lone), replace(rest, unconfirmed=rest.lone)
            return _relative_tail(own, rest, self.params.relative_margin)
        return {slot for slot in slots
                if self._fails(self._tests * tail(slot, self.last_pairs),
                               lambda slot=slot: tail(slot, self.last_now),
                               lambda slot=slot: self._tests * tail(slot, self.last_pairs,
                                                                    lone=True))}


    def orphaned(self, slots: list[int], judges: list[Hashable], ego: Hashable,
                 names: list[Hashable], scored: list[np.ndarray]) -> set[int]:
        """Record this step's orphan boxes of every slot (``names``: their collaborator
        ids, ``ego`` the ego's): boxes that some source of ``judges`` (EGO and slots; not
        the slot itself) leaves unconfirmed, with no box of any judge within ``orphan_m``
        (from this step's :func:`box_status` of every pair), in :attr:`last_orphans`
        (slot -> (orphans, boxes) over the window, and this step's), among each slot's
        boxes ``scored`` (bool per box: scored at least ``orphan_score``); the slots whose
        orphans exceed the share ``orphan_rate`` significantly over the window (one-sided
        binomial, level alpha over the consistency tests' Bonferroni) and this step's alone
        have a p-value of at most ``recent``."""
        self.last_orphans, self.last_witnessed = {}, {}
        for slot, name, counted in zip(slots, names, scored, strict=True):
            others = [self._status[slot, judge] for judge in judges if judge != slot]
            count = self._status[slot, EGO].matched.shape[0]
            near = np.full(count, np.inf)
            doubts = np.zeros(count, dtype=int)  # judges leaving the box unconfirmed
            for judged in others:
                near = np.minimum(near, judged.gap)
                doubts += judged.unconfirmed
            orphan = (doubts > 0) & (near > self.params.orphan_m) & counted
            now = (int(orphan.sum()), int(counted.sum()),
                   int(np.sum(orphan & (doubts >= self.params.witness_judges))))
            history = self._orphans.setdefault((ego, name), deque(maxlen=self.params.window))
            history.append(now)
            window = np.sum(history, axis=0).tolist()
            self.last_orphans[slot] = ((window[0], window[1]), now[:2])
            self.last_witnessed[slot] = (window[2], now[2])
        return {slot for slot in slots
                if self._fails(self._tests * self._orphan_tail(
                    *self.last_orphans[slot][0], self.last_witnessed[slot][0]),
                               lambda slot=slot: self._orphan_tail(
                                   *self.last_orphans[slot][1], self.last_witnessed[slot][1]))}

    def _orphan_tail(self, orphans: int, boxes: int, witnessed: int) -> float:
        """The one-sided binomial p-value of ``orphans`` among ``boxes`` against
        ``orphan_rate``; with ``use_witnessed`` the smaller of it over ``1 -
        witnessed_level`` and that of ``witnessed`` orphans against ``witnessed_rate`` over
        ``witnessed_level`` (a weighted Bonferroni inside the orphan test, which leaves the
        other consistency tests' as it was); 1 without boxes."""
        if not boxes:
            return 1.0
        tail = float(bdtrc(orphans - 1, boxes, self.params.orphan_rate))
        if self.params.use_witnessed:
            share = self.params.witnessed_level
            tail = min(1.0, tail / (1.0 - share), float(bdtrc(
                witnessed - 1, boxes, self.params.witnessed_rate)) / share)
        return tail


def _relative_tail(own: PairEvidence, rest: PairEvidence, margin: float) -> float:
    """One-sided p-value of a collaborator's share of unconfirmed boxes (``own``: its boxes
    as the others judge them) exceeding ``margin`` times the pooled share of the other
    collaborators' boxes (``rest``: as judged by everyone but it): a Wald z-test of the
    difference ``p_own - margin p_rest``; 1 where either side has nothing judged or
    ``own`` has no unconfirmed box (no evidence against it)."""
    n_own = own.matches + own.conflicts + own.unconfirmed
    n_rest = rest.matches + rest.conflicts + rest.unconfirmed
    if n_own == 0 or n_rest == 0 or own.unconfirmed == 0:
        return 1.0
    p_own, p_rest = own.unconfirmed / n_own, rest.unconfirmed / n_rest
    variance = _share_variance(p_own, n_own, p_rest, n_rest, margin)
    if variance == 0.0:
        # both shares at 0 or 1 (e.g. every own box unconfirmed, none of the others'): the
        # Wald variance vanishes; one pseudo-count each way (Agresti-Caffo) gives it
        variance = _share_variance((own.unconfirmed + 1) / (n_own + 2), n_own,
                                   (rest.unconfirmed + 1) / (n_rest + 2), n_rest, margin)
    return float(ndtr(-(p_own - margin * p_rest) / np.sqrt(variance)))


def _share_variance(p_own: float, n_own: int, p_rest: float, n_rest: int,
                    margin: float) -> float:
    """Variance of ``p_own - margin p_rest`` for two independent binomial shares."""
    return p_own * (1.0 - p_own) / n_own + margin**2 * p_rest * (1.0 - p_rest) / n_rest


def _offsets(observation: Mapping[str, Any], filled: np.ndarray) -> np.ndarray:
    """(len(filled), 3) the signed correction of each filled slot's reported pose,
    ``reported^-1 * aligned``, in the collaborator's reported frame (m, m, rad): a fixed
    spoof is a fixed offset there, whatever the two agents' motion."""
    if "collab_reported_poses" not in observation:
        raise ValueError("defend's offset test reads observation['collab_reported_poses'] "
                         "(the aligned observation's reported relative poses); give it, or "
                         "use_offset=False")
    reported = np.asarray(observation["collab_reported_poses"], dtype=float)[filled]
    aligned = np.asarray(observation["collab_rel_poses"], dtype=float)[filled]
    offset = se2_compose(se2_inverse(reported), aligned).reshape(-1, 3)
    offset[:, 2] = wrap_angle(offset[:, 2])
    return offset


class Shades(NamedTuple):
    """Every source's boxes as view blockers, ego frame: ``boxes`` (M, 3) their centre x,
    y and height (m); ``owner`` (M,) the position in ``keys`` of the source that reported
    each."""

    boxes: np.ndarray
    owner: np.ndarray
    keys: tuple

    def without(self, key: Hashable) -> np.ndarray:
        """(m, 3) the boxes of every source but ``key``."""
        return self.boxes[self.owner != self.keys.index(key)]


def _shades(sources: Mapping[Hashable, tuple[np.ndarray, np.ndarray]]) -> Shades:
    """:class:`Shades` of :func:`_sources`' sources (built once per step and pose)."""
    counts = [boxes.shape[0] for boxes, _ in sources.values()]
    return Shades(np.concatenate([boxes[:, _OCCLUDER] for boxes, _ in sources.values()]),
                  np.repeat(np.arange(len(counts)), counts), tuple(sources))


def _sources(observation: Mapping[str, Any], filled: np.ndarray
             ) -> dict[Hashable, tuple[np.ndarray, np.ndarray]]:
    """The ego (key EGO) and each filled slot: (boxes (k, 7), origin (2,)), ego frame."""
    own = np.asarray(observation["boxes"], dtype=float)[np.asarray(observation["box_mask"]) > 0]
    sources: dict[Hashable, tuple[np.ndarray, np.ndarray]] = {EGO: (own, np.zeros(2))}
    boxes = np.asarray(observation["collab_boxes"], dtype=float)
    masks = np.asarray(observation["collab_box_mask"]) > 0
    poses = np.asarray(observation["collab_rel_poses"], dtype=float)
    for slot in filled:
        sources[int(slot)] = (boxes[slot][masks[slot]], poses[slot, :2])
    return sources
