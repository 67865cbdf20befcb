"""Compiled (numba) matching rounds of one RoCo collaborator (:func:`attempt_rounds`).

A RoCo call runs a few match-optimise rounds per collaborator; in Python each round
costs several small array operations and two crossings into compiled code on top of
the work itself. Here the whole loop of ``roco._attempt`` runs in one compiled call
from the same kernels (:func:`~roco_env.policies.matching_kernels.scored_pairs`,
:func:`~roco_env.policies.pose_kernels.solve_pose_edges`) with the same stopping
rules; a round whose matching needs the full Kuhn-Munkres assignment (scipy's) hands
the collaborator back to the Python loop (tests/test_roco_kernels.py compares the two).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from roco_env.policies.matching_kernels import placed_centres, scored_pairs
from roco_env.policies.pose_kernels import solve_pose_edges, wald_statistic

__all__ = ["attempt_rounds"]


@njit(cache=True)
def _matches(pose, own_poses, land_xy, tau2, lam, use_edge, land_features, box_features,
             radius2, tau1, cache):
    """One ``StarGraphMatcher.match`` under ``pose`` (3,) with gate ``tau2`` (m) when the
    assignment's shortcut applies: (shortcut applied?, landmark (P,), box (P,), new cache);
    no landmarks or no boxes: no matches, the cache kept."""
    if land_xy.shape[0] == 0 or own_poses.shape[0] == 0:
        return True, cache[0][:0].copy(), cache[0][:0].copy(), cache
    single, land, box, _, _, _, _, cache = scored_pairs(
        land_xy, placed_centres(pose, own_poses), tau2, lam, use_edge, land_features,
        box_features, radius2, tau1, cache,
    )
    return single, land, box, cache


@njit(cache=True)
def attempt_rounds(start, own_poses, own_info, own_cov, land_poses, land_features, land_cov,
                   box_features, prior_z, prior_info, tau2, coarse_tau2, lam, use_edge, radius2,
                   tau1, min_matches, rounds, kernel, delta, max_iterations, tolerance, min_diag,
                   inlier_chi2, fit_tolerance):
    """RoCo's match-optimise rounds for one collaborator (``roco._attempt`` with per-round
    single-vertex solves).

    start (3,): first pose estimate T_{j->i}; own_poses (K, 3) / own_info (K, 3, 3) /
    own_cov (K, 3, 3): its boxes (its frame), their information and covariance;
    land_poses (L, 3) / land_cov (L, 3, 3): the map's landmarks (ego frame) and their
    covariance; land_features (5, L) / box_features (5, K): the pose features; prior_z
    (3,) / prior_info (3, 3): the prior edge (reported pose). Matching settings as
    ``StarGraphMatcher`` (tau2, coarse_tau2 m, coarse_tau2 <= 0: no coarse gate; lam = 0:
    no distance term); at most ``rounds`` rounds; solver settings as
    :func:`~roco_env.policies.pose_kernels.solve_pose_edges`.

    When the rounds end solved with at least ``min_matches`` edges of chi2 <=
    ``inlier_chi2`` and ``fit_tolerance`` > 0, also the significance test's statistic
    (``roco._correction_statistic``: :func:`~roco_env.policies.pose_kernels.wald_statistic`
    with the covariance of box minus landmark, LM stop ``fit_tolerance``); else nan.

    Returns (done, pose (3,), landmark ids (P,), box ids (P,), solved, chi2 (P,),
    landmarks (P, 3), rounds run, solver iterations, statistic); done = False when a
    round's matching needs the full assignment (the rest is then meaningless).
    """
    empty = np.zeros(0, dtype=np.int64)
    cache = (empty, empty.copy(), empty.copy(), empty.copy(), np.zeros(0))
    land_xy = np.ascontiguousarray(land_poses[:, :2])
    pose = start.copy()
    match_land, match_box = empty.copy(), empty.copy()
    chi2, landmarks = np.zeros(0), np.zeros((0, 3))
    solved, outer, solver = False, 0, 0
    for _ in range(rounds):
        single, land, box, cache = _matches(pose, own_poses, land_xy, tau2, lam, use_edge,
                                            land_features, box_features, radius2, tau1, cache)
        if single and outer == 0 and land.size < min_matches and coarse_tau2 > 0:
            single, land, box, cache = _matches(pose, own_poses, land_xy, coarse_tau2, lam,
                                                use_edge, land_features, box_features, radius2,
                                                tau1, cache)
        if not single:
            return (False, pose, match_land, match_box, solved, chi2, landmarks, outer, solver,
                    np.nan)
        if outer and _same(land, match_land) and _same(box, match_box):
            break
        outer += 1
        match_land, match_box = land, box
        solved = land.size >= min_matches
        if not solved:
            break
        landmarks = land_poses[match_land]
        pose, chi2, _, _, iterations, _ = solve_pose_edges(
            pose, landmarks, own_poses[match_box], own_info[match_box], prior_z, prior_info,
            kernel, delta, max_iterations, tolerance, min_diag,
        )
        solver += iterations
    statistic = np.nan
    if solved and fit_tolerance > 0 and np.count_nonzero(chi2 <= inlier_chi2) >= min_matches:
        statistic = wald_statistic(
            pose, landmarks, own_poses[match_box], own_cov[match_box] + land_cov[match_land],
            prior_z, kernel, delta, max_iterations, fit_tolerance, min_diag,
        )
    return True, pose, match_land, match_box, solved, chi2, landmarks, outer, solver, statistic


@njit(cache=True)
def _same(a, b):
    """``np.array_equal`` of two 1-d integer arrays."""
    if a.size != b.size:
        return False
    for k in range(a.size):
        if a[k] != b[k]:
            return False
    return True
