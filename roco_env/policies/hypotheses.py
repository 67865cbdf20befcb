"""Pose hypotheses for one collaborator and their evidence (aliasing-aware alignment).

In a repetitive scene (a full parking lot: cars every 2.5 m) a collaborator's boxes
fit the ego's boxes almost equally well at several global shifts, and a matcher that
starts from the reported pose converges to whichever shift lies nearest. This module
makes the shifts explicit:

1. :func:`generate_hypotheses`: the relative rotation error is voted from the box
   headings (modulo pi) of nearby box pairs, then the translation error from their
   centre offsets on a 2D grid (a Hough vote); the ``max_hypotheses`` strongest local
   maxima within ``search_radius`` become hypotheses (plus the reported pose and any
   extra seeds, e.g. a temporal track's prediction);
2. refinement (:func:`refine_terms`): nearest-neighbour matching within ``refine_gate``
   and a robust single-vertex pose-graph solve (the solver of
   :func:`~roco_env.policies.posegraph.optimize_pose`), twice, in one compiled pass;
3. :func:`score_hypotheses`: a log-likelihood ratio per hypothesis in chi-square units
   (-2 ln L): every collaborator box explained by an ego box gains
   ``outlier_chi2 - chi2(pair)`` (position with both boxes' covariances, heading modulo pi,
   log sizes), switchable terms add the mirror image with a penalty for ego boxes left
   unexplained inside the collaborator's observed disk (free space), the mutual
   detections (an ego box where the hypothesis puts the collaborator's own vehicle, a
   collaborator box where it puts the ego); priors (the reported pose, a track) subtract
   their Mahalanobis distance. Distinctive objects need no weight of their own: the log
   sizes and headings in the pair chi2 are what makes a box distinctive, in the
   likelihood's own units (an explicit rarity weight was measured to add nothing and
   would make the margin's scale depend on the scene).

Poses are T_{j->i} (x m, y m, yaw rad) in the ego frame; boxes (K, 7) as everywhere.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np

from roco_env.policies.hypothesis_kernels import (
    BoxTerms,
    EvidenceSettings,
    VoteSettings,
    hypothesis_scores,
    rotation_votes,
    translation_votes,
    vote_peaks,
)
from roco_env.policies.landmarks import AlignmentInputs, split_rows
from roco_env.policies.pose_kernels import RefineSettings
from roco_env.policies.posegraph import solver_settings
from roco_env.schema import spec

__all__ = [
    "BoxSet",
    "EvidenceParams",
    "box_set",
    "box_sets",
    "generate_hypotheses",
    "evidence_terms",
    "refine_terms",
    "score_hypotheses",
    "translation_peaks",
]


# The 5-cell box filter of the rotation votes (read-only).
_SMOOTHING = np.ones(5)
_SMOOTHING.flags.writeable = False

# LM cap and relative-decrease stop of a refinement solve (they only steer the hypothesis).
_REFINE_ITERATIONS, _REFINE_TOLERANCE = 50, 1e-4

@dataclass(frozen=True)
class EvidenceParams:
    """Hypothesis search and evidence (units m, deg, chi-square units = -2 ln L).

    search_radius (m) / search_yaw_deg (deg): translation / rotation errors searched around
    the reported pose; vote_bin (m): translation vote cell; max_hypotheses: local maxima
    kept; vote_floor: share of the strongest vote a local maximum needs (weaker ones
    cannot compete and are not refined); refine_gate (m): matching gate of the
    refinement; outlier_chi2: what an unexplained box costs (a pair gains
    ``outlier_chi2 - chi2``, never less than 0); pose_slack_t (m) / pose_slack_r_deg
    (deg): std added to every pair for the residual misfit of a hypothesis; size_sigma:
    std of one box's log size (l, w, h); free_space_penalty: chi2 cost of an ego box
    inside the collaborator's observed disk that none of its boxes explains. use_*: the
    switches of the terms (module docstring).
    """

    search_radius: float = spec(7.0, low=0.0, low_open=True,
                                doc="translation errors searched around the reported pose, m")
    search_yaw_deg: float = spec(8.0, low=0.0, low_open=True,
                                 doc="rotation errors searched around the reported pose, deg")
    vote_bin: float = spec(0.5, low=0.0, low_open=True, doc="translation vote cell, m")
    max_hypotheses: int = spec(6, low=1, doc="local maxima of the votes kept")
    vote_floor: float = spec(0.2, low=0.0, high=1.0, high_open=True,
                             doc="share of the strongest vote a local maximum needs")
    refine_gate: float = spec(1.0, low=0.0, low_open=True,
                              doc="matching gate of the refinement, m")
    outlier_chi2: float = spec(16.0, low=0.0, low_open=True,
                               doc="chi2 cost of an unexplained box")
    pose_slack_t: float = spec(0.1, low=0.0, low_open=True,
                               doc="std added to every pair for a hypothesis' misfit, m")
    pose_slack_r_deg: float = spec(0.3, low=0.0, low_open=True,
                                   doc="std added to every pair for a hypothesis' misfit, deg")
    size_sigma: float = spec(0.06, low=0.0, low_open=True, doc="std of one box's log size")
    free_space_penalty: float = spec(2.0, low=0.0, doc="chi2 cost of an ego box inside the "
                                     "collaborator's observed disk that it does not explain")
    use_size: bool = spec(True, doc="log sizes in the pair chi2")
    use_free_space: bool = spec(True, doc="the free-space term")
    use_mutual_detection: bool = spec(True, doc="the mutual-detection term")


@dataclass(frozen=True)
class BoxSet:
    """One agent's boxes in its own frame: poses (K, 3), log sizes (K, 3) (l, w, h),
    information (K, 3, 3) (box frame, as the pose graph uses it), var_t (K,) the mean of
    the centre's x and y variances (m^2), var_r (K,) the heading variance (rad^2),
    range (m): the largest distance of a box from the agent (the radius of its observed
    disk)."""

    poses: np.ndarray
    log_sizes: np.ndarray
    information: np.ndarray
    var_t: np.ndarray
    var_r: np.ndarray
    range: float

    @cached_property
    def terms(self) -> tuple:
        """These boxes as the compiled evidence takes them: the
        :class:`~roco_env.policies.hypothesis_kernels.BoxTerms`, as a plain tuple."""
        return tuple(BoxTerms(self.poses, self.log_sizes, self.var_t, self.var_r,
                              float(self.range)))


def _box_arrays(
    boxes: np.ndarray, poses: np.ndarray, information: np.ndarray, xy_covariance: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per box: log sizes (K, 3), var_t (K,), var_r (K,) and distance from the agent (K,)
    (:class:`BoxSet`), every value from its own box only; xy_covariance (K, 2, 2): the
    covariance of the box centre."""
    sizes = np.maximum(boxes[:, 3:6], 1e-3)
    # sigma_x^2 + sigma_y^2 is the trace of the centre's covariance (rotation invariant).
    var_t = 0.5 * (xy_covariance[:, 0, 0] + xy_covariance[:, 1, 1])
    return np.log(sizes), var_t, 1.0 / information[:, 2, 2], np.hypot(poses[:, 0], poses[:, 1])


def box_set(boxes: np.ndarray, poses: np.ndarray, information: np.ndarray) -> BoxSet:
    """:class:`BoxSet` of validated boxes (K, 7) with their poses (K, 3) and information
    (K, 3, 3) from :func:`~roco_env.policies.landmarks.prepare_inputs`."""
    xy_cov = np.linalg.inv(information[:, :2, :2]) if boxes.shape[0] else np.zeros((0, 2, 2))
    log_sizes, var_t, var_r, distance = _box_arrays(boxes, poses, information, xy_cov)
    return BoxSet(poses, log_sizes, information, var_t, var_r, _reach(distance))


def box_sets(boxes: Sequence[np.ndarray], inputs: AlignmentInputs) -> list[BoxSet]:
    """:func:`box_set` of every agent (ego first): boxes[a] (K_a, 7) validated, with the
    poses and information of ``inputs`` (:func:`~roco_env.policies.landmarks.prepare_inputs`),
    derived in one pass over all agents' boxes (per-agent calls cost more in overhead;
    every value depends on its own box only). The centres' covariances are the xy blocks
    of ``inputs.all_covariance``, which RoCo computes anyway (the information has no
    xy-yaw terms, so they are the inverses of the information's xy blocks, to rounding:
    tests/test_hypothesis_kernels.py)."""
    arrays = _box_arrays(np.concatenate(boxes), inputs.all_poses, inputs.all_information,
                         inputs.all_covariance[:, :2, :2])
    log_sizes, var_t, var_r = (split_rows(values, inputs.offsets) for values in arrays[:3])
    # Every agent's reach in one reduction (0 without boxes; the empty ones are skipped,
    # so each start's segment ends where the next agent with boxes begins).
    starts, stops = inputs.offsets[:-1], inputs.offsets[1:]
    reach = np.zeros(starts.size)
    if arrays[3].size:
        reach[stops > starts] = np.maximum.reduceat(arrays[3], starts[stops > starts])
    return [
        BoxSet(inputs.poses[a], log_sizes[a], inputs.information[a], var_t[a], var_r[a],
               float(reach[a]))
        for a in range(starts.size)
    ]


def _reach(distance: np.ndarray) -> float:
    """The largest box distance (m; 0 without boxes): the radius of the observed disk."""
    return float(distance.max()) if distance.size else 0.0


@lru_cache(maxsize=16)
def _vote_settings(p: EvidenceParams) -> VoteSettings:
    """The vote settings of ``p`` (:class:`~roco_env.policies.hypothesis_kernels.VoteSettings`,
    computed once per parameter set): rotation search half-width
    and 0.25 deg cell (rad), its bin count and pair radius (m); the translation grid's pair
    radius (m), search half-width (m), cell (m) and cells per axis; 2 size_sigma^2 (0 =
    sizes not used); the heading std weighing the translation votes (3 deg, in rad); the
    peaks' suppression radius (cells^2), max_hypotheses and vote_floor."""
    half, cell = np.deg2rad(p.search_yaw_deg), np.deg2rad(0.25)
    return VoteSettings(
        float(half), float(cell), int(np.ceil(2 * half / cell)), float(p.search_radius + 2.0),
        float(p.search_radius * np.sqrt(2.0)), float(p.search_radius), float(p.vote_bin),
        int(np.ceil(2 * p.search_radius / p.vote_bin)),
        2.0 * p.size_sigma**2 if p.use_size else 0.0, float(np.deg2rad(3.0)),
        (1.25 / p.vote_bin) ** 2,  # lattice pitches (2.5 m) stay apart
        int(p.max_hypotheses), float(p.vote_floor),
    )


def generate_hypotheses(
    ego: BoxSet, collab: BoxSet, reported: np.ndarray, p: EvidenceParams
) -> np.ndarray:
    """Initial poses (H, 3) of the strongest votes (module docstring, step 1); the first
    row is the vote maximum; empty (0, 3) when no box pair lies within the search.

    The rotation is the strongest (5-cell smoothed) bin of the heading-difference votes;
    the translation votes are smoothed by a 3x3 box sum (a true offset splits its votes
    over neighbouring cells); peaks are taken in decreasing vote order, above
    ``vote_floor`` of the strongest, away from the earlier ones. The votes and the peak
    scan are compiled loops (:mod:`roco_env.policies.hypothesis_kernels`)."""
    settings = _vote_settings(p)
    votes = tuple(settings)
    counts, n_pairs = rotation_votes(ego.terms, collab.terms, reported, votes)
    if n_pairs == 0:
        return np.zeros((0, 3))
    smooth = np.convolve(counts, _SMOOTHING, mode="same")
    peak = int(np.argmax(smooth))  # the first maximum: smooth[peak] is smooth.max()
    half, cell = settings.half, settings.cell
    rotation = -half + (peak + 0.5) * cell if smooth[peak] > 0 else 0.0
    rotated = reported + np.array([0.0, 0.0, rotation])
    return translation_peaks(ego, collab, rotated, p)


def translation_peaks(
    ego: BoxSet, collab: BoxSet, rotated: np.ndarray, p: EvidenceParams, most: int | None = None
) -> np.ndarray:
    """The translation vote's peaks (H, 3) around ``rotated`` (3,) at its rotation (step 1 of
    the module docstring, the compiled vote and peak scan), strongest first: at most
    ``most`` of them (default ``max_hypotheses``)."""
    settings = _vote_settings(p)
    if most is not None:
        settings = settings._replace(max_hypotheses=int(most))
    votes = tuple(settings)
    grid = translation_votes(ego.terms, collab.terms, rotated, votes)
    return vote_peaks(grid, np.argsort(-grid, axis=None), rotated, votes)


def refine_terms(
    p: EvidenceParams, kernel: str | None, kernel_delta: float, min_matches: int
) -> tuple:
    """The refinement's settings (module docstring, step 2) as
    :func:`~roco_env.policies.pose_kernels.refine_pose` and ``refine_starts`` take them:
    the :class:`~roco_env.policies.pose_kernels.RefineSettings` (gate m, min_matches, the
    solver's settings) as a plain tuple, the solver's a plain tuple too (numba types a
    plain tuple argument in C: pose_kernels' module docstring). Up to two rounds of
    nearest matching within ``refine_gate`` and a robust pose solve (the second only when
    the matches changed); a start matching fewer than ``min_matches`` boxes refines to
    nothing."""
    solver = solver_settings(kernel, kernel_delta, _REFINE_ITERATIONS, _REFINE_TOLERANCE)
    return tuple(RefineSettings(float(p.refine_gate), int(min_matches), tuple(solver)))


def evidence_terms(p: EvidenceParams) -> tuple:
    """The evidence settings as the compiled evidence takes them
    (:class:`~roco_env.policies.hypothesis_kernels.EvidenceSettings` as a plain tuple):
    pose slack variances m^2 and rad^2, 2 size_sigma^2 (0 = sizes not used), outlier_chi2,
    free_space_penalty, use_free_space, use_mutual_detection."""
    return tuple(EvidenceSettings(
        float(p.pose_slack_t**2), float(np.deg2rad(p.pose_slack_r_deg) ** 2),
        2.0 * p.size_sigma**2 if p.use_size else 0.0, float(p.outlier_chi2),
        float(p.free_space_penalty), bool(p.use_free_space), bool(p.use_mutual_detection)))


def score_hypotheses(
    ego: BoxSet, collab: BoxSet, poses: np.ndarray, p: EvidenceParams
) -> np.ndarray:
    """Evidence (H,) of each hypothesis pose (H, 3), in chi2 units (module docstring, step 3;
    priors not included), in one compiled pass
    (:func:`~roco_env.policies.hypothesis_kernels.hypothesis_scores`).

    Only boxes inside the other agent's observed disk under *every* hypothesis count
    (otherwise a hypothesis that pulls more boxes into the overlap scores higher). Per
    box, the best pair's gain ``outlier_chi2 - chi2 > 0`` (chi2 from position, heading
    modulo pi and, when used, log sizes, with both boxes' variances and the pose slack:
    :func:`~roco_env.policies.hypothesis_kernels.best_pair_gains`); the direct detections
    count an ego box where the hypothesis puts the collaborator's vehicle that no
    collaborator box explains (nobody detects itself), and a collaborator box where it
    puts the ego.
    """
    return hypothesis_scores(ego.terms, collab.terms, np.ascontiguousarray(poses, dtype=float),
                             evidence_terms(p))
