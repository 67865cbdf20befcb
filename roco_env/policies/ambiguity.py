"""Which directions of a collaborator's relative pose the shared boxes determine.

Some scenes cannot fix every component of T_{j->i} (x m, y m, yaw rad, ego frame): a
row of cars 2.5 m apart fits the ego's boxes as well one stall over, a queue of evenly
spaced cars on a straight road as well one car along the road. :func:`diagnose` tells,
for a chosen pose ``pose`` of collaborator j among candidate poses (in roco_antialias: the
decision's refined hypotheses, i.e. the vote peaks within ``search_radius`` of the
reported pose, the reported pose and the track's prediction), which directions are
*undetermined*:

1. **Spectrum (local).** Every collaborator box mapped by ``pose`` is paired with the
   nearest ego box within ``refine_gate`` (m). The pairs' Fisher information of the pose,
   ``A = sum J^T W J`` (position residual with variance ``v_p + v_q + pose_slack_t^2``,
   heading residual with ``w_p + w_q + pose_slack_r^2``, as the evidence weighs them;
   J the residual's derivative in (x, y, yaw)), is taken in *scaled* coordinates
   ``z = (x / distinct_t, y / distinct_t, yaw / distinct_r)``. From its inverse, the pose's
   covariance: the yaw is undetermined when its marginal std exceeds the hypotheses'
   rotation search (``search_yaw_deg``, 8 deg), a translation direction when the
   translation's marginal std along it exceeds their translation search
   (``search_radius``, 7 m): the pairs leave it as open as the search itself. (A fit that
   pins the yaw to 1.5 deg still beats a reported yaw 3-5 deg off: a tighter rule,
   std > ``distinct_r_deg``, kept such reported yaws in the stress search's traffic jams
   and made 1% of the poses worse.) Fewer than ``min_matches`` pairs determine nothing.
2. **Rivals (global).** Each candidate pose h (the refined hypotheses) distinct from
   ``pose`` (more than ``distinct_t`` m or ``distinct_r_deg`` deg away) whose score is
   within ``min_margin`` of the pose's, ``E(h) - c(h) >= E(pose) - c(pose) - min_margin``
   (E the evidence of :func:`~roco_env.policies.hypotheses.score_hypotheses`, chi2 units;
   c any prior other than the reported pose's, e.g. a temporal track's), explains the
   boxes (nearly) as well, or better: the displacement ``h - pose`` is undetermined. Poses
   found outside the candidates (``beyond``; in roco_antialias those beyond the
   hypotheses' search that explain the boxes far better, and, for a pose of few pairs,
   those matched by one pair fewer than ``min_matches`` that come within ``min_margin``)
   are rivals too; an alias beyond every search that explains them no better goes
   unnoticed.
3. **Subspace.** Translations and the yaw are kept apart (a direction mixing metres and
   degrees would trade a heading error for a position error): the undetermined
   translation directions are those of step 1, then the rivals' shifts, largest first,
   each adding its part orthogonal to the directions so far when that part is longer than
   ``distinct_t`` m (a shorter one is the same direction up to the refinement's noise);
   the yaw is undetermined after step 1 or when a rival turns by more than
   ``distinct_r_deg`` deg. The determined directions are the orthogonal complement.
4. **Margin of the determined part.** With every prior in the score (the reported pose's
   too), ``S(h) = E(h) - c(h) - prior(h)``: the best score among the candidates whose
   offset from the pose, projected onto the determined directions, is not distinct
   (within the thresholds above), minus the best among the others (0 without any), as
   the decision's margin is taken. A pose whose determined part wins by less than
   ``min_margin`` is not trusted there either (a poorly matched hypothesis far from the
   reported pose scores below 0).

The rule and its thresholds use the aligner's own settings (no new knob): the rival
margin is the decision's ``min_margin`` (20 chi2 units: a likelihood ratio of e^10), the
scale is the distinctness of two hypotheses (1 m, 1 deg), the pairing gate the
refinement's (1 m).

5. **What may be applied** (:meth:`Ambiguity.projected`). The open translation
   directions keep the reported pose; every rival shifted along them shares the pose's
   determined part. An open yaw keeps the reported yaw, and the translation follows the
   pose turned to it about the pairs' (information-weighted) centroid: the boxes pin
   their centroid, and a turn about it moves the collaborator's origin by the turn times
   its distance, so the fitted translation holds only with the fitted yaw (turning about
   the centroid is the translation's estimate given the yaw). A translation direction
   the pairs themselves pin poorly (step 1) is tied to the rest of the fit in ways a
   turn does not undo: then, as when nothing is determined, the reported pose is kept
   (:attr:`Ambiguity.applicable`). :meth:`Ambiguity.significant` tests the applied part
   with the pairs' information (Wald).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.stats import chi2 as chi2_distribution

from roco_env.geometry import wrap_angle
from roco_env.policies.hypotheses import BoxSet
from roco_env.policies.pose_kernels import pair_information
from roco_env.policies.prior_free import poses_distinct

if TYPE_CHECKING:
    from roco_env.policies.antialias import AntiAliasParams

__all__ = ["Ambiguity", "diagnose", "scaled_offsets"]


@dataclass(frozen=True)
class Ambiguity:
    """The diagnosis of one collaborator's pose (module docstring).

    pose (3,): the diagnosed T_{j->i} (x m, y m, yaw rad); scale (3,): the scaled
    coordinates' units (m, m, rad); undetermined (k, 3): orthonormal basis of the
    undetermined directions in scaled coordinates (k = 0: fully determined, 3: nothing
    determined); information (3, 3): the pairs' information of the pose in scaled
    coordinates; matches: the pairs; rivals (R, 3): the candidate poses that explain the
    boxes nearly as well; margin: how decisively the candidates' scores (priors included)
    pick the pose's determined part (chi2 units, step 4 of the module docstring; NaN when
    nothing is determined); weak_translation: step 1 left a translation direction open
    (the pairs themselves pin it poorly); box_std: the boxes' own precision (m), the root
    of the ego's and the collaborator's median centre variances (x and y mean) summed: how
    well one pair pins its centre (NaN: not known).
    """

    pose: np.ndarray
    scale: np.ndarray
    undetermined: np.ndarray
    information: np.ndarray
    matches: int
    rivals: np.ndarray
    margin: float = float("nan")
    weak_translation: bool = False
    box_std: float = float("nan")

    @property
    def determined(self) -> int:
        """How many directions the boxes determine (0-3)."""
        return 3 - self.undetermined.shape[0]

    @property
    def yaw_open(self) -> bool:
        """Whether the yaw is undetermined."""
        return bool((np.abs(self.undetermined[:, 2]) > 0.5).any())

    @property
    def applicable(self) -> bool:
        """Whether a determined part may be applied (module docstring, step 5): some
        direction is determined and every open translation direction is one a rival is
        shifted along (step 2), not one the pairs themselves pin poorly (step 1)."""
        return self.determined > 0 and not self.weak_translation

    def projected(self, reported: np.ndarray) -> np.ndarray:
        """The pose (3,) that keeps ``reported`` (3,) along the undetermined directions and
        takes the diagnosed pose's determined part (step 5): with the yaw open, the pose
        turned to the reported yaw about the pairs' centroid (the translation given the
        yaw); then the translation's offset from the reported one without its components
        along the open translation directions."""
        reported = np.asarray(reported, dtype=float)
        pose = self.pose.copy()
        if self.yaw_open:
            turn = wrap_angle(reported[2] - pose[2])
            centre = pose[:2] + self._centroid_offset()
            c, s = np.cos(turn), np.sin(turn)
            pose[:2] = centre + np.array([[c, -s], [s, c]]) @ (pose[:2] - centre)
            pose[2] = reported[2]
        moves = self.undetermined[np.abs(self.undetermined[:, 2]) <= 0.5, :2]
        shift = pose[:2] - reported[:2]
        pose[:2] = reported[:2] + shift - moves.T @ (moves @ shift)
        return pose

    def _centroid_offset(self) -> np.ndarray:
        """The pairs' information-weighted centroid (2,) (m, ego frame) relative to the
        diagnosed pose's position: (A_yθ, -A_xθ) / A_xx in metres (the centres' levers
        about the collaborator's origin, :func:`~roco_env.policies.pose_kernels.pair_information`)."""
        info = self.information
        return np.array([info[1, 2], -info[0, 2]]) / info[0, 0] * (self.scale[0] / self.scale[2])

    def statistic(self, reported: np.ndarray) -> float:
        """Wald statistic of the applied determined part (chi-square with
        :attr:`determined` dof when ``reported`` is right along the determined
        directions): the correction's coordinates a in an orthonormal basis B of the
        determined subspace (scaled), weighed by the inverse of their covariance
        ``B C B^T``, C the inverse of :attr:`information` (the yaw's row and column left
        out when the yaw is open: the translation is then estimated given the reported
        yaw). NaN when nothing is determined."""
        if self.determined == 0:
            return float("nan")
        reported = np.asarray(reported, dtype=float)
        basis = _complement(self.undetermined)
        delta = self.projected(reported) - reported
        delta[2] = wrap_angle(delta[2])
        coords = basis @ (delta / self.scale)
        kept = [0, 1] if self.yaw_open else [0, 1, 2]
        inverse = np.zeros((3, 3))
        inverse[np.ix_(kept, kept)] = np.linalg.inv(self.information[np.ix_(kept, kept)])
        covariance = basis @ inverse @ basis.T
        return float(coords @ np.linalg.solve(covariance, coords))

    def move_statistic(self, reported: np.ndarray, pose: np.ndarray) -> float:
        """What the pairs' information says for moving ``reported`` (3,) to ``pose`` (3,):
        ``z^T A z`` with z their difference in scaled coordinates (the turn wrapped) and A
        :attr:`information` (chi2 units: the Gaussian part of how much better ``pose``
        explains the pairs, without the gain of boxes paired at one pose and not at the
        other; chi-square with 3 dof when ``reported`` is right and ``pose`` the pairs' fit)."""
        offset = scaled_offsets(np.asarray(pose, dtype=float)[None],
                                np.asarray(reported, dtype=float), self.scale)[0]
        return float(offset @ self.information @ offset)

    @property
    def translation_std(self) -> float:
        """How well the pairs pin the collaborator's origin: the root of the translation's
        marginal variance (x plus y, m^2) under :attr:`information` (the yaw's uncertainty
        included, levered by the pairs' distance); inf when the information is singular."""
        try:
            covariance = np.linalg.inv(self.information)
        except np.linalg.LinAlgError:
            return float("inf")
        return float(np.sqrt(max(covariance[0, 0] + covariance[1, 1], 0.0)) * self.scale[0])

    def significant(self, reported: np.ndarray, significance: float | None) -> bool:
        """Whether the determined part of the correction is beyond the estimation noise:
        :meth:`statistic` > ``chi2.ppf(significance, determined)``; ``significance`` None
        or 0 = any correction counts; never when nothing is determined."""
        if self.determined == 0:
            return False
        if not significance:
            return True
        threshold = chi2_distribution.ppf(significance, self.determined)
        return bool(self.statistic(reported) > threshold)

    def describe(self) -> str:
        """The undetermined directions in words, e.g. ``"undetermined along (0.98, 0.17)"``
        (a translation direction in the ego frame), ``"nothing determined"``."""
        if self.determined == 0:
            return "nothing determined"
        parts = []
        for direction in self.undetermined:
            if abs(direction[2]) > 0.5:
                parts.append("yaw")
            else:
                unit = direction[:2] / np.hypot(*direction[:2])
                parts.append(f"({unit[0]:.2f}, {unit[1]:.2f})")
        return "undetermined along " + ", ".join(parts)


def _complement(basis: np.ndarray) -> np.ndarray:
    """Orthonormal rows (3 - k, 3) spanning the complement of the orthonormal rows
    ``basis`` (k, 3)."""
    if basis.shape[0] == 0:
        return np.eye(3)
    _, _, vt = np.linalg.svd(basis, full_matrices=True)
    return vt[basis.shape[0]:]


def diagnose(
    ego: BoxSet,
    collab: BoxSet,
    candidates: np.ndarray,
    best: int,
    rival_score: np.ndarray,
    score: np.ndarray,
    p: AntiAliasParams,
    *,
    slack: tuple[float, float],
    beyond: np.ndarray | None = None,
) -> Ambiguity:
    """The undetermined directions of collaborator j's pose ``candidates[best]`` (module
    docstring).

    ego / collab: the agents' boxes (:class:`~roco_env.policies.hypotheses.BoxSet`);
    candidates (H, 3): the refined hypotheses (T_{j->i}, x m, y m, yaw rad), the diagnosed
    pose among them; rival_score (H,): their evidence
    (:func:`~roco_env.policies.hypotheses.score_hypotheses`) minus every prior term but the
    reported pose's (e.g. a track's), chi2 units: finds the rivals; score (H,): minus the
    reported pose's too (:attr:`Ambiguity.margin`); p: the aligner's settings
    (``refine_gate`` pairs the boxes, the search's ``search_radius`` / ``search_yaw_deg``
    bound the spectrum's stds, ``min_margin`` (chi2 units) is how close a rival's score must
    come, ``distinct_t`` (m) / ``distinct_r_deg`` (deg) when two poses differ
    (:func:`~roco_env.policies.prior_free.poses_distinct`) and the units of the scaled
    coordinates, ``min_matches`` the fewest pairs that determine anything); slack: the pose
    slack's variances (m^2, rad^2) that weigh the pairs, as the evidence's settings hold
    them (:func:`~roco_env.policies.hypotheses.evidence_terms`); beyond (R, 3): rivals found
    outside the candidates (in roco_antialias: poses beyond the hypotheses' search that
    explain the boxes far better than the pose, or matched by too few pairs to be
    hypotheses that explain them about as well), their shifts open directions as the
    candidates' rivals do.
    """
    candidates = np.asarray(candidates, dtype=float).reshape(-1, 3)
    pose = candidates[best]
    scale = np.array([p.distinct_t, p.distinct_t, np.deg2rad(p.distinct_r_deg)])
    information, matches = pair_information(
        (ego.poses, ego.var_t, ego.var_r), (collab.poses, collab.var_t, collab.var_r), pose,
        float(p.refine_gate), *slack)
    information *= scale[:, None] * scale
    if matches < p.min_matches:
        return Ambiguity(pose, scale, np.eye(3), information, matches, candidates[:0],
                         weak_translation=True)
    # Step 1: the spectrum; step 2: the rivals.
    limits = ((p.search_radius / scale[0]) ** 2, (np.deg2rad(p.search_yaw_deg) / scale[2]) ** 2)
    moves, yaw_open = _spectrum(information, limits)
    weak_translation = bool(moves)
    offset = scaled_offsets(candidates, pose, scale)
    distinct_rows = poses_distinct(candidates, pose, p)
    rival = (rival_score >= rival_score[best] - p.min_margin) & distinct_rows
    beyond = np.zeros((0, 3)) if beyond is None else np.asarray(beyond, dtype=float).reshape(-1, 3)
    rivals = np.concatenate([offset[rival], scaled_offsets(beyond, pose, scale)])
    # Step 3: translation directions (largest rival shift first) and the yaw axis.
    if rivals.shape[0]:
        shifts = rivals[:, :2]
        for shift in shifts[np.argsort(-np.hypot(shifts[:, 0], shifts[:, 1]), kind="stable")]:
            rest = shift - sum(((m @ shift) * m for m in moves), np.zeros(2))
            if len(moves) < 2 and np.hypot(*rest) > 1.0:
                moves.append(rest / np.hypot(*rest))
        yaw_open = yaw_open or np.abs(rivals[:, 2]).max() > 1.0
    directions = [[m[0], m[1], 0.0] for m in moves] + ([[0.0, 0.0, 1.0]] if yaw_open else [])
    undetermined = np.array(directions, dtype=float).reshape(-1, 3)
    return Ambiguity(pose, scale, undetermined, information, matches,
                     np.concatenate([candidates[rival], beyond]),
                     _determined_margin(offset, undetermined, score, distinct_rows, p),
                     weak_translation, _box_std(ego, collab))


def _box_std(ego: BoxSet, collab: BoxSet) -> float:
    """The boxes' own precision (:attr:`Ambiguity.box_std`, m): the root of the summed
    median centre variances (x and y mean) of the two agents' boxes; NaN without boxes."""
    if not ego.var_t.size or not collab.var_t.size:
        return float("nan")
    return float(np.sqrt(np.median(ego.var_t) + np.median(collab.var_t)))


def scaled_offsets(poses: np.ndarray, pose: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Offsets (H, 3) of ``poses`` (H, 3) from ``pose`` (3,), the turn wrapped, in the
    scaled coordinates of ``scale`` (3,)."""
    offset = poses - pose
    offset[:, 2] = wrap_angle(offset[:, 2])
    return offset / scale


def _spectrum(
    information: np.ndarray, limits: tuple[float, float]
) -> tuple[list[np.ndarray], bool]:
    """Step 1 of the module docstring: the translation directions (unit (2,) each) along
    which the marginal variance under the scaled ``information`` (3, 3) exceeds
    ``limits[0]``, and whether the yaw's exceeds ``limits[1]`` (scaled units squared).

    The pairs' information has the form [[a, 0, b], [0, a, c], [b, c, d]] (a > 0 once a pair
    exists), so its inverse is known in closed form: the yaw's variance is 1 / s with the
    Schur complement s = d - (b^2 + c^2) / a (>= the headings' information > 0), the
    translation's covariance I / a + v v^T / (a^2 s) with v = (b, c): variance 1 / a across
    v and 1 / a + |v|^2 / (a^2 s) along it."""
    a, b, c, d = information[0, 0], information[0, 2], information[1, 2], information[2, 2]
    lever = float(np.hypot(b, c))
    schur = d - lever**2 / a
    if 1.0 / a > limits[0]:
        moves = [np.array([1.0, 0.0]), np.array([0.0, 1.0])]
    elif lever > 0 and 1.0 / a + lever**2 / (a**2 * schur) > limits[0]:
        moves = [np.array([b, c]) / lever]
    else:
        moves = []
    return moves, bool(1.0 / schur > limits[1])


def _determined_margin(
    offset: np.ndarray, undetermined: np.ndarray, total: np.ndarray, distinct_rows: np.ndarray,
    p: AntiAliasParams,
) -> float:
    """Step 4 of the module docstring: offsets (H, 3) of the candidates from the pose (scaled
    coordinates), the undetermined basis (k, 3), the candidates' scores (H,) and which
    offsets are distinct (H,) (those of the determined part when nothing is open; ``p``'s
    thresholds)."""
    if undetermined.shape[0] == 3:
        return float("nan")
    other = distinct_rows
    if undetermined.shape[0]:
        determined_part = offset - (offset @ undetermined.T) @ undetermined
        scale = np.array([p.distinct_t, p.distinct_t, np.deg2rad(p.distinct_r_deg)])
        other = poses_distinct(determined_part * scale, np.zeros(3), p)
    runner_up = total[other].max() if other.any() else 0.0
    return float(total[~other].max() - runner_up)
