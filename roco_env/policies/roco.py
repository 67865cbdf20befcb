"""RoCo (ACM MM 2024) as the paper describes it: graph-guided matching + robust pose graph.

:func:`roco_align` works on plain arrays in the ego's reported frame (ego =
identity, metres/radians). Collaborators' messages are processed one by one
against a growing landmark set that starts with the ego's boxes:

1. map the collaborator's boxes into the ego frame with its current pose estimate
   (initially the reported relative pose);
2. match them to the landmarks (:mod:`roco_env.policies.matching`: star graphs,
   initial nearest match within tau2, S = S_edge + lambda * S_dis, Kuhn-Munkres,
   reject S < tau1); a first round with fewer than ``min_matches`` matches is redone
   with the wider gate ``coarse_tau2`` (an addition to the paper: at sigma 0.8 the
   tails of the relative error push true partners beyond tau2);
3. update the collaborator's pose from the matches: the robust pose graph (box edges
   with the box-uncertainty information and a robust kernel; an ego -> agent prior
   edge from the reported relative pose with information from ``prior_sigma_t`` /
   ``prior_sigma_r_deg``; Levenberg-Marquardt capped at ``max_solver_iterations``;
   ego fixed) restricted to this agent's vertex against the current map, or, with
   ``joint_every_round=True``, the whole graph (every accepted agent and every
   landmark seen by >= 2 agents). Restricted to one vertex, the landmarks are held
   fixed at the boxes that created them, so an edge's residual carries both boxes'
   errors: its information is ``(Sigma_box + Sigma_landmark)^-1``
   (``round_information="difference"``, the default there; ``"box"``: the box's alone, as the
   joint graph weighs it, where landmarks are free). With the box's alone, a landmark
   from a box far less certain than the collaborator's (an RSU's diagonal view of a car
   whose heading a CAV sees along its axis: yaw sigma 0.1 against 0.004 rad) makes a
   true match an outlier for the kernel and the inlier test;
4. re-match with the updated pose; repeat 2-3 until the matching stops changing
   (at most ``max_outer_iterations`` rounds; one round when ``iterate=False``).

Matched boxes become observations of their landmarks; unmatched boxes become new
landmarks. After the last message, one joint robust solve over all agents and
all shared landmarks gives the final poses (the per-round solves only steer the
matching; restricting them to one vertex makes a frame ~3x cheaper).

Do-no-harm rule: a collaborator's correction is applied (and its boxes enter the
map) only when (a) at least ``min_matches`` of its boxes are matched, (b) at
least ``min_matches`` of those edges are inliers at the optimum
(``e^T Omega e <= inlier_chi2``, Omega the rounds' edge information, step 3) and (c)
the evidence says the reported pose is wrong beyond the estimation noise (significance
test). For (c) the collaborator's
pose is re-fitted to its matched edges alone (no prior edge, robust kernel as used),
each edge with the information of the *difference* of the two boxes,
``(Sigma_box + Sigma_landmark)^-1`` (a landmark's covariance is that of the box that
created it); the correction ``d = fitted - reported`` is then weighed by its
covariance, the robust sandwich ``A^-1 B A^-1`` from the fit's Hessian
(A = sum w J^T Omega J, B = sum w^2 J^T Omega J, w the kernel's IRLS weights): the
Wald statistic ``d^T A B^-1 A d`` is chi-square with 3 dof when the reported pose is
right. (The plain cost drop "chi2 at reported - chi2 at fit" is the same test for
least squares, but the kernel shrinks it, mean ~2.2 instead of 3 on the realistic
detector, so it passes too few real corrections; the sandwich keeps the nominal
level.) The correction is applied when the statistic exceeds
``chi2.ppf(significance, 3)``, else the prior is kept with the reason "correction
not significant". The test relies on *calibrated* box uncertainties (the realistic
detector's are: calibration = 1.0): over-confident boxes let noise-floor corrections
through, under-confident ones hide real errors. ``significance=None`` (or 0) switches
it off and restores the older rule (c'): the robust cost at the optimised pose is
lower than at the reported one (which the optimum nearly always satisfies). A rejected
collaborator keeps its reported pose (applied=False, with the reason) and its boxes
stay out of the map; one that fails is retried once after the others, against the
larger map.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.stats import chi2 as chi2_distribution

from roco_env.policies.adapter import ArrayAlignmentPolicy, ObservationView, collaborator_keys
from roco_env.policies.base import AlignmentResult
from roco_env.policies.landmarks import (
    AlignmentInputs,
    UncertaintyParams,
    landmark_graph,
    pairs_from_observations,
    params_from_kwargs,
    prepare_inputs,
    prior_information,
    split_rows,
)
from roco_env.policies.matching import MatchingParams, pose_features
from roco_env.policies.pooled import PooledSignificance
from roco_env.policies.pose_kernels import (
    AgentBoxes,
    LandmarkMap,
    Observations,
    RoundSettings,
    RoundState,
    attempt_rounds,
    committed_map,
    inverse_covariances,
)
from roco_env.policies.posegraph import (
    ROBUST_KERNELS,
    PoseGraphResult,
    edge_chi2,
    optimize,
    robust_kernel,
    solver_settings,
)
from roco_env.schema import spec

__all__ = [
    "NOT_SIGNIFICANT",
    "ROUND_INFORMATION",
    "RoCoParams",
    "RoCoPolicy",
    "RoCoPolicyParams",
    "roco_align",
    "roco_solve",
]

# Start of the reason for a prior kept by the significance test: the matched evidence is
# consistent with the reported pose (a checked prior, unlike "no boxes" or too few matches).
NOT_SIGNIFICANT = "correction not significant"

# RoCoParams.round_information: the edge information of the matching rounds' solves.
ROUND_INFORMATION = ("difference", "box")

# Relative cost decrease that ends a per-round single-vertex solve: those solves only
# steer the matching (the final joint solve uses the solver's default, 1e-6).
_ROUND_TOLERANCE = 1e-4
# Relative cost decrease that ends the significance test's fit (the solver's default).
_FIT_TOLERANCE = 1e-6

# A collaborator's rounds start without matches, chi2 or landmarks (never written: the
# rounds replace them with new arrays).
_NO_INDEX, _NO_CHI2, _NO_LANDMARKS = np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros((0, 3))


@dataclass(frozen=True)
class RoCoParams(MatchingParams, UncertaintyParams):
    """RoCo parameters (matching ones from :class:`MatchingParams`; units m, rad unless noted).

    robust_kernel: Cauchy is the default because a mismatched box is a gross outlier and
    Huber still pulls on it linearly (tests/test_roco.py: 3 of 10 boxes misplaced by 1.2 m
    leave 0.05 m error with Cauchy, 0.2 m with Huber, 0.3 m without a kernel).
    round_information: the information of an edge in the single-vertex rounds (and so of
    the kernel's weights and the inlier test): "difference" = ``(Sigma_box +
    Sigma_landmark)^-1``, "box" = the box's own (module docstring, step 3); None (default):
    "difference", or with joint_every_round "box" (the rounds then solve the whole graph,
    where landmarks are free and every edge keeps its box's information, so "difference"
    is a ValueError there).
    significance: a correction is applied when its Wald statistic exceeds
    chi2.ppf(significance, 3) (module docstring). Relies on calibrated box uncertainties.
    On the realistic detector at sigma 0, 0.99 corrects ~1-2% of slots (0.95: ~7-10%,
    0.999: ~0.3%).
    coarse_tau2: large errors push true partners beyond tau2; the later rounds use tau2
    again.
    """

    iterate: bool = spec(True, doc="re-match after each solve")
    max_outer_iterations: int = spec(10, low=1, doc="cap of the match-solve rounds")
    robust_kernel: str | None = spec("cauchy", choices=(*ROBUST_KERNELS, None),
                                     doc="robust kernel of the pose graph (None: least "
                                     "squares)")
    kernel_delta: float = spec(float(np.sqrt(7.815)), low=0.0, low_open=True,
                               doc="the kernel's width in whitened units (default: sqrt of "
                               "the 95% chi-square quantile for 3 dof)")
    prior_sigma_t: float = spec(1.0, low=0.0, low_open=True,
                                doc="std of the reported relative poses' translation, m")
    prior_sigma_r_deg: float = spec(1.0, low=0.0, low_open=True,
                                    doc="std of the reported relative poses' rotation, deg")
    min_matches: int = spec(3, low=1, doc="matches (and inliers) the do-no-harm rule needs")
    inlier_chi2: float = spec(11.345, low=0.0, low_open=True,
                              doc="an edge is an inlier when e^T Omega e <= inlier_chi2")
    max_solver_iterations: int = spec(1000, low=1, doc="Levenberg-Marquardt cap")
    joint_every_round: bool = spec(False, doc="solve the whole graph in every matching "
                                   "round (slower) instead of the collaborator's vertex "
                                   "against the current map, with one joint solve at the end")
    coarse_tau2: float | None = spec(6.0, doc="gate (m, > tau2) that redoes a first round "
                                     "with fewer than min_matches matches within tau2 "
                                     "(None: the paper's single gate)")
    significance: float | None = spec(0.99, low=0.0, high=1.0, high_open=True,
                                      doc="confidence of the do-no-harm significance test "
                                      "(None or 0: no test, any cost decrease applies)")
    round_information: str | None = spec(None, choices=(*ROUND_INFORMATION, None),
                                         doc="edge information of the single-vertex rounds")

    def __post_init__(self) -> None:
        """The rules joining fields (each field's own: its spec)."""
        MatchingParams.__post_init__(self)
        UncertaintyParams.__post_init__(self)
        if self.joint_every_round and self.round_information == "difference":
            raise ValueError("round_information='difference' weighs single-vertex rounds; "
                             "joint_every_round=True solves the whole graph, where each edge "
                             "keeps its box's information: set round_information='box'")
        if self.coarse_tau2 is not None and not self.coarse_tau2 > self.tau2:
            raise ValueError(f"coarse_tau2 must be None or > tau2={self.tau2}; got "
                             f"{self.coarse_tau2}")

    @property
    def difference_rounds(self) -> bool:
        """Whether the rounds weigh an edge by box minus landmark: ``round_information``
        resolved (None is "difference", or "box" with joint_every_round)."""
        return self.round_information != "box" and not self.joint_every_round


class _Map:
    """Landmarks (ego frame) with their observations, and the accepted agents' poses.

    landmarks: the :class:`~roco_env.policies.pose_kernels.LandmarkMap` (poses (M, 3);
    the matcher's :func:`~roco_env.policies.matching.pose_features` (5, M), kept in step
    with the poses; covariance (M, 3, 3) of the box that created each landmark, in the box
    frame: an upper bound once more observations refine it, used by the significance
    test); observations: which box of which agent sees which landmark
    (:class:`~roco_env.policies.pose_kernels.Observations`); box_features: per agent,
    the pose features of its boxes in its own frame.
    """

    def __init__(self, inputs: AlignmentInputs, ego_covariance: np.ndarray):
        ego_poses = inputs.poses[0].copy()
        self.landmarks = LandmarkMap(ego_poses, pose_features(ego_poses), ego_covariance.copy())
        # Every agent's boxes' features in its own frame (fixed), computed in one pass.
        self.box_features = [
            features.T for features in split_rows(pose_features(inputs.all_poses).T, inputs.offsets)
        ]
        count = ego_poses.shape[0]
        self.observations = Observations(np.zeros(count, dtype=np.int64), np.arange(count),
                                         np.arange(count))
        self.agent_poses: dict[int, np.ndarray] = {0: np.zeros(3)}

    def shared(self, extra_land: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Landmark ids seen by >= 2 agents once ``extra_land`` gets one more observation,
        and which of the stored observations are of those landmarks (bool mask)."""
        land = self.observations.land
        counts = np.bincount(land, minlength=self.landmarks.poses.shape[0])
        counts[extra_land] += 1
        is_shared = counts >= 2
        return np.nonzero(is_shared)[0], is_shared[land]


@dataclass
class _Attempt:
    """One collaborator's match-optimise rounds: where they ended
    (:class:`~roco_env.policies.pose_kernels.RoundState`: pose, matches, their chi2 and
    landmarks, rounds and solver iterations), the significance test's statistic (None
    when the rounds did not compute it) and, when the rounds solve the whole graph, the
    last joint solve (result, agent ids, shared landmark ids)."""

    state: RoundState
    statistic: float | None = None
    joint: tuple[PoseGraphResult, np.ndarray, np.ndarray] | None = None


@lru_cache(maxsize=16)
def _prior_info(p: RoCoParams) -> np.ndarray:
    """Information (3, 3) of the prior edges (read-only: shared by every call with ``p``)."""
    info = prior_information(p.prior_sigma_t, np.deg2rad(p.prior_sigma_r_deg))
    info.flags.writeable = False
    return info


@lru_cache(maxsize=16)
def _round_settings(p: RoCoParams) -> tuple[tuple, tuple, tuple]:
    """The settings of ``p`` as :func:`~roco_env.policies.pose_kernels.attempt_rounds`
    takes them (plain tuples), computed once per parameter set: the
    :class:`~roco_env.policies.pose_kernels.RoundSettings` (gates m, coarse -1 = none;
    min_matches, the round cap, the prior edges' information, inlier_chi2, the
    significance fit's stop (0 = no significance test), whether the rounds' edges carry
    the information of box minus landmark (``round_information``), whether they solve the
    whole graph), the matcher's settings and the rounds' solver (LM stop
    ``_ROUND_TOLERANCE``)."""
    rounds = RoundSettings(
        float(p.tau2),
        -1.0 if p.coarse_tau2 is None else float(p.coarse_tau2),
        int(p.min_matches),
        int(p.max_outer_iterations) if p.iterate else 1,
        _prior_info(p),
        float(p.inlier_chi2),
        _FIT_TOLERANCE if p.significance else 0.0,
        p.difference_rounds,
        bool(p.joint_every_round),
    )
    solver = solver_settings(p.robust_kernel, p.kernel_delta, p.max_solver_iterations,
                             _ROUND_TOLERANCE)
    return tuple(rounds), tuple(p.match_settings()), tuple(solver)


def _joint_solve(
    inputs: AlignmentInputs,
    world: _Map,
    p: RoCoParams,
    state: RoundState | None = None,
    agent: int = 0,
) -> tuple[PoseGraphResult, np.ndarray, np.ndarray]:
    """Optimise the map's agents (+ ``agent`` at ``state.pose`` with its matches, when a
    round state is given) and every landmark seen by >= 2 agents.

    Returns (result, agent ids, landmark ids) (vertex order = id order, extra agent last).
    """
    known = sorted(world.agent_poses)
    poses = [world.agent_poses[a] for a in known]
    observed = world.observations
    match_land = observed.land[:0] if state is None else state.match_land
    match_box = observed.box[:0] if state is None else state.match_box
    if state is not None:
        known, poses = [*known, agent], [*poses, state.pose]
    shared, keep = world.shared(match_land)
    obs_agent = np.concatenate([observed.agent[keep], np.full(match_land.size, agent)])
    obs_box = np.concatenate([observed.box[keep], match_box])
    obs_land = np.searchsorted(shared, np.concatenate([observed.land[keep], match_land]))
    agent_ids = np.array(known)
    graph = landmark_graph(
        inputs,
        agent_ids,
        np.stack(poses),
        world.landmarks.poses[shared],
        obs_agent,
        obs_box,
        obs_land,
        _prior_info(p),
    )
    solution = optimize(
        graph,
        fixed=0,
        kernel=p.robust_kernel,
        kernel_delta=p.kernel_delta,
        max_iterations=p.max_solver_iterations,
    )
    return solution, agent_ids, shared


def _round_information(
    inputs: AlignmentInputs, world: _Map, agent: int, state: RoundState, p: RoCoParams
) -> np.ndarray:
    """Information (P, 3, 3) of the collaborator's matched edges as its rounds weigh them
    (module docstring, step 3): ``(Sigma_box + Sigma_landmark)^-1`` when
    :attr:`RoCoParams.difference_rounds`, else the box's own."""
    if p.difference_rounds:
        box_covariance = inputs.all_covariance[inputs.offsets[agent] + state.match_box]
        return inverse_covariances(box_covariance + world.landmarks.covariance[state.match_land])
    return inputs.information[agent][state.match_box]


def _attempt(
    inputs: AlignmentInputs,
    world: _Map,
    agent: int,
    p: RoCoParams,
    start: np.ndarray,
    boxes: AgentBoxes,
) -> _Attempt:
    """Match-optimise rounds for one collaborator (steps 1-4 of the module docstring; its
    boxes: ``boxes``), starting from the pose estimate ``start`` (3,), in one compiled call
    (:func:`~roco_env.policies.pose_kernels.attempt_rounds`, which also computes the
    significance test's statistic). When the rounds solve the whole graph, they pause
    before each solve, made here (:func:`_joint_solve`), and go on from its result."""
    rounds, match, solver = _round_settings(p)
    boxes, landmarks = tuple(boxes), tuple(world.landmarks)
    state = RoundState(np.array(start, dtype=float), _NO_INDEX, _NO_INDEX, False, _NO_CHI2,
                       _NO_LANDMARKS, 0, 0)
    joint = None
    while True:
        state, statistic, paused = attempt_rounds(tuple(state), boxes, landmarks, rounds, match,
                                                  solver)
        state = RoundState(*state)
        if not paused:
            break
        joint = _joint_solve(inputs, world, p, state, agent)
        solution, _, shared = joint
        state = state._replace(
            pose=solution.agents[-1].copy(),
            chi2=solution.obs_chi2[-state.match_box.size:].copy(),
            landmarks=solution.landmarks[np.searchsorted(shared, state.match_land)],
            iterations=state.iterations + solution.iterations,
        )
    return _Attempt(state, None if np.isnan(statistic) else float(statistic), joint)


@lru_cache(maxsize=16)
def _significance_threshold(significance: float) -> float:
    """chi2 quantile with 3 dof (one SE(2) pose) at ``significance``."""
    return float(chi2_distribution.ppf(significance, 3))


def _rejection(
    inputs: AlignmentInputs,
    world: _Map,
    agent: int,
    att: _Attempt,
    p: RoCoParams,
    waived: bool = False,
) -> tuple[str, float]:
    """Why the do-no-harm rule rejects the attempt ("" when it is accepted) and the
    significance test's statistic (NaN when not computed; the compiled rounds compute it,
    module docstring: the Wald statistic of the collaborator's pose re-fitted to its
    matched edges alone). ``waived``: the statistic is computed but does not decide
    (:mod:`roco_env.policies.pooled`)."""
    state = att.state
    if not state.solved:
        return f"{state.match_land.size} matches < min_matches={p.min_matches}", np.nan
    inliers = int(np.count_nonzero(state.chi2 <= p.inlier_chi2))
    if inliers < p.min_matches:
        return f"{inliers} inlier matches < min_matches={p.min_matches}", np.nan
    if p.significance:
        statistic = att.statistic
        threshold = _significance_threshold(p.significance)
        if not (statistic > threshold or waived):
            return (
                f"{NOT_SIGNIFICANT}: Wald {statistic:.2f} <= {threshold:.2f} "
                f"(chi2 3 dof, significance={p.significance})"
            ), statistic
        return "", statistic
    own = inputs.poses[agent][state.match_box]
    info = _round_information(inputs, world, agent, state, p)  # as state.chi2's edges were
    reported = inputs.reported[agent - 1]
    chi2_reported = edge_chi2(np.broadcast_to(reported, own.shape), state.landmarks, own, info)
    cost_optimised = robust_kernel(state.chi2, p.robust_kernel, p.kernel_delta)[0].sum()
    cost_reported = robust_kernel(chi2_reported, p.robust_kernel, p.kernel_delta)[0].sum()
    if not cost_optimised < cost_reported:
        return "optimised pose does not explain the boxes better than the reported one", np.nan
    return "", np.nan


def _store_joint(world: _Map, joint: tuple[PoseGraphResult, np.ndarray, np.ndarray]) -> None:
    solution, agent_ids, shared = joint
    for vertex, agent_id in enumerate(agent_ids):
        world.agent_poses[int(agent_id)] = solution.agents[vertex]
    world.landmarks.poses[shared] = solution.landmarks
    world.landmarks.features[:, shared] = pose_features(solution.landmarks)


def _commit(world: _Map, agent: int, att: _Attempt, boxes: AgentBoxes) -> None:
    """Accept the attempt of the collaborator ``agent`` (its boxes: ``boxes``): store
    optimised poses, observations and new landmarks."""
    if att.joint is not None:
        _store_joint(world, att.joint)
    state = att.state
    world.agent_poses[agent] = state.pose
    # Matched boxes become observations, the others new landmarks (one compiled pass).
    landmarks, observations = committed_map(
        state.pose, state.match_land, state.match_box, tuple(boxes), agent,
        tuple(world.landmarks), tuple(world.observations),
    )
    world.landmarks, world.observations = LandmarkMap(*landmarks), Observations(*observations)


def roco_align(
    ego_boxes: np.ndarray,
    ego_unc: np.ndarray,
    collab_boxes: Sequence[np.ndarray],
    collab_unc: Sequence[np.ndarray],
    reported: np.ndarray,
    *,
    initial: np.ndarray | None = None,
    waived: Sequence[int] = (),
    **params,
) -> AlignmentResult:
    """Correct the collaborators' relative poses with RoCo.

    ego_boxes (K0, 7) / ego_unc (K0, 3) in the ego frame; collab_boxes[j] (K_j, 7) /
    collab_unc[j] (K_j, 3) in collaborator j's own frame (uncertainty = sigma_x m,
    sigma_y m, sigma_yaw rad, agent frame); reported (N, 3) reported T_{j->i}.
    initial (N, 3): where the matching rounds start (default: the reported poses; the
    prior edges and the do-no-harm test always use the reported ones). waived:
    collaborators (indices into collab_boxes) whose significance test is computed but
    does not decide, because their reported poses are known to carry errors
    (:mod:`roco_env.policies.pooled`; :class:`RoCoPolicy` decides it over the frames).
    params: fields of :class:`RoCoParams`. Returns corrected T_{j->i} and diagnostics.
    """
    p = params_from_kwargs(RoCoParams, params, "roco")
    inputs = prepare_inputs(ego_boxes, ego_unc, collab_boxes, collab_unc, reported, p)
    waived = frozenset(int(j) for j in waived)
    if not waived <= set(range(inputs.n_collaborators)):
        raise ValueError(f"waived must hold collaborator indices in [0, "
                         f"{inputs.n_collaborators}); got {sorted(waived)}")
    return roco_solve(inputs, p, initial, waived=waived)


def roco_solve(
    inputs: AlignmentInputs,
    p: RoCoParams,
    initial: np.ndarray | None = None,
    excluded: frozenset[int] = frozenset(),
    waived: frozenset[int] = frozenset(),
) -> AlignmentResult:
    """:func:`roco_align` on validated inputs (:func:`~roco_env.policies.landmarks.prepare_inputs`)
    and checked parameters. Collaborator slots in ``excluded`` are treated as if they sent
    no boxes (reason "no boxes"; their reported poses are kept); in ``waived`` the
    significance test does not decide (:func:`roco_align`)."""
    start = inputs.reported if initial is None else np.asarray(initial, dtype=float)
    if start.shape != inputs.reported.shape or not np.all(np.isfinite(start)):
        raise ValueError(
            f"initial must be finite with the shape of reported {inputs.reported.shape}; "
            f"got {start.shape}"
        )
    # Each agent's box covariances (K_a, 3, 3), rows of the inputs' all_covariance.
    covariance = split_rows(inputs.all_covariance, inputs.offsets)
    world = _Map(inputs, covariance[0])
    n = inputs.n_collaborators
    boxes = [None] + [
        AgentBoxes(inputs.poses[a], inputs.information[a], covariance[a], world.box_features[a],
                   inputs.reported[a - 1])
        for a in range(1, n + 1)
    ]
    reasons = {j: "" for j in range(n)}
    statistics = np.full(n, np.nan)
    outer = solver = 0
    has_boxes = [inputs.poses[a].shape[0] > 0 and a - 1 not in excluded for a in range(n + 1)]
    queue = list(range(1, n + 1))
    retried: set[int] = set()
    accepted_since_joint = False
    while queue:
        agent = queue.pop(0)
        if not has_boxes[agent]:
            reasons[agent - 1] = "no boxes"
            continue
        att = _attempt(inputs, world, agent, p, start[agent - 1], boxes[agent])
        outer, solver = outer + att.state.outer, solver + att.state.iterations
        reasons[agent - 1], statistics[agent - 1] = _rejection(
            inputs, world, agent, att, p, agent - 1 in waived)
        if not reasons[agent - 1]:
            _commit(world, agent, att, boxes[agent])
            accepted_since_joint = True
            # The map grew: collaborators that failed earlier get one more try.
            failed = [a for a in range(1, agent) if reasons[a - 1] and a not in retried]
            failed = [a for a in failed if has_boxes[a] and a not in queue]
            retried.update(failed)
            queue.extend(failed)
    if accepted_since_joint and not p.joint_every_round:
        joint = _joint_solve(inputs, world, p)
        _store_joint(world, joint)
        solver += joint[0].iterations
    applied = np.array([j + 1 in world.agent_poses for j in range(n)], dtype=bool)
    corrected = inputs.reported.copy()
    for j in np.nonzero(applied)[0]:
        corrected[j] = world.agent_poses[j + 1]
    shared, keep = world.shared(np.zeros(0, dtype=np.int64))
    observed = world.observations
    return AlignmentResult(
        corrected=corrected,
        applied=applied,
        matched_pairs=pairs_from_observations(
            observed.agent[keep], observed.box[keep], observed.land[keep]
        ),
        landmarks=world.landmarks.poses[shared],
        outer_iterations=outer,
        solver_iterations=solver,
        reason="; ".join(f"slot {j}: {r}" for j, r in reasons.items() if r),
        slot_reasons=tuple(reasons[j] for j in range(n)),
        slot_statistics=tuple(statistics.tolist()),
    )


@dataclass(frozen=True)
class RoCoPolicyParams(RoCoParams):
    """:class:`RoCoPolicy`'s parameters: RoCo's and the pooled significance test's."""

    pooled_significance: float | None = spec(
        None, low=0.0, high=1.0, low_open=True, high_open=True,
        doc="confidence of the pooled test over each collaborator's last frames (None: "
        "every frame's significance test decides alone)")

    def __post_init__(self) -> None:
        RoCoParams.__post_init__(self)
        if self.pooled_significance is not None and not self.significance:
            raise ValueError("pooled_significance needs RoCo's significance test; got "
                             f"significance={self.significance}")


class RoCoPolicy(ArrayAlignmentPolicy):
    """RoCo as an env policy: ``RoCoPolicy(**params)(obs, info=None) -> action (N, 3)``.

    pooled_significance: None (default: every frame's significance test decides alone)
    or the confidence, in (0, 1), of the pooled test over each collaborator's last
    frames (:mod:`roco_env.policies.pooled`): once it shows that collaborator's reported
    poses carry errors, its frame-by-frame test no longer keeps them. The policy then
    keeps a history per ego and collaborator (``info["agent"]``,
    ``info["collaborators"]``; a call without them is a ValueError): call :meth:`reset`
    between episodes. Needs the significance test (``significance`` not None or 0).
    """

    def __init__(self, **params) -> None:
        checked = params_from_kwargs(RoCoPolicyParams, params, "roco")
        super().__init__(roco_align, checked,
                         {k: v for k, v in params.items() if k != "pooled_significance"})
        self.pooled = None
        if checked.pooled_significance is not None:
            self.pooled = PooledSignificance(checked.pooled_significance)
            self.keeps_state = "per ego and collaborator (info['agent'], info['collaborators'])"

    def reset(self) -> None:
        """Forget the pooled test's history (call between episodes)."""
        super().reset()
        if self.pooled is not None:
            self.pooled.reset()

    def align_view(
        self, view: ObservationView, observation: dict, info: dict | None
    ) -> AlignmentResult:
        """:func:`roco_align`, the significance test waived for the collaborators the pooled
        test finds wrong; their statistics extend the history."""
        if self.pooled is None:
            return super().align_view(view, observation, info)
        keys = collaborator_keys(info, view.slots, "roco with pooled_significance")
        waived = [j for j, key in enumerate(keys) if self.pooled.waived(key)]
        result = self._align(*view.arrays, waived=waived, **self._kwargs)
        self.pooled.record(keys, result.slot_statistics)
        return result
