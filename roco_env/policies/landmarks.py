"""Shared plumbing of the landmark-based aligners (CoAlign, RoCo).

* :func:`prepare_inputs` validates the array call of ``coalign_align``/``roco_align``
  and turns box uncertainties into information matrices.
* :func:`landmark_graph` builds the pose graph "agents + shared landmarks" from a
  list of box observations.
* :func:`pairs_from_observations` turns landmark observations into the
  ``matched_pairs`` rows of :class:`~roco_env.policies.base.AlignmentResult`.

Agent index convention inside the aligners: 0 = ego, ``j + 1`` = collaborator slot ``j``.
Poses are in the ego's reported frame (ego = identity); metres and radians.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from roco_env.geometry import validate_boxes
from roco_env.policies.posegraph import PoseGraph
from roco_env.schema import build, spec

__all__ = [
    "AlignmentInputs",
    "UncertaintyParams",
    "prepare_inputs",
    "box_information",
    "landmark_graph",
    "pairs_from_observations",
    "params_from_kwargs",
    "prior_information",
    "require_sigmas",
    "split_rows",
]


def split_rows(values: np.ndarray, offsets: np.ndarray) -> list[np.ndarray]:
    """``values`` cut along its first axis at ``offsets`` (A + 1,) into A views (rows
    ``offsets[a]:offsets[a + 1]``): ``np.split(values, offsets[1:-1], axis=0)`` without
    its per-piece overhead (the alignment stages cut every per-box array per agent)."""
    bounds = offsets.tolist()
    return [values[start:stop] for start, stop in zip(bounds[:-1], bounds[1:], strict=True)]


@dataclass(frozen=True)
class AlignmentInputs:
    """Validated aligner inputs.

    poses: per agent (ego first) its boxes' BEV poses (K_a, 3) (x, y, yaw) in its own frame.
    information: per agent (K_a, 3, 3) information of each box-pose measurement,
        expressed in the residual (box) frame.
    reported: (N, 3) reported relative poses T_{j->i} of the collaborators.
    all_poses (B, 3), all_information (B, 3, 3): every agent's rows stacked (``poses`` and
        ``information`` are views into them); box k of agent a is row ``offsets[a] + k``.
    """

    poses: list[np.ndarray]
    information: list[np.ndarray]
    reported: np.ndarray
    all_poses: np.ndarray
    all_information: np.ndarray
    offsets: np.ndarray

    @property
    def n_collaborators(self) -> int:
        return self.reported.shape[0]

    @functools.cached_property
    def all_covariance(self) -> np.ndarray:
        """Covariance (B, 3, 3) of every box pose (box frame), the inverse of
        ``all_information`` matrix by matrix; computed once per inputs (RoCo and the
        hypothesis evidence both use it)."""
        return np.linalg.inv(self.all_information)


@dataclass(frozen=True)
class UncertaintyParams:
    """How box uncertainties become information: sigma floors (m, rad) and the
    sigmas used for non-finite entries (sigma_x m, sigma_y m, sigma_yaw rad)."""

    sigma_floor_xy: float = spec(0.02, low=0.0, low_open=True,
                                 doc="floor of a box's sigma_x and sigma_y, m")
    sigma_floor_yaw: float = spec(0.002, low=0.0, low_open=True,
                                  doc="floor of a box's sigma_yaw, rad")
    default_sigma: tuple[float, float, float] = spec(
        (0.5, 0.5, 0.1), doc="sigma_x m, sigma_y m, sigma_yaw rad of a non-finite entry")

    def __post_init__(self) -> None:
        require_sigmas(self.default_sigma, "default_sigma")


def require_sigmas(value: Sequence[float], name: str) -> np.ndarray:
    """``value`` as an array (3,) of standard deviations (m, m, rad); ValueError naming
    ``name`` unless it holds 3 finite values > 0 (a rule a field's spec cannot state)."""
    sigma = np.asarray(value, dtype=float)
    if sigma.shape != (3,) or not np.all(np.isfinite(sigma) & (sigma > 0)):
        raise ValueError(f"{name} must be 3 finite values > 0 (m, m, rad); got {value!r}")
    return sigma


def box_information(
    poses: np.ndarray,
    uncertainty: np.ndarray,
    floor_xy: float,
    floor_yaw: float,
    default: tuple[float, float, float],
) -> np.ndarray:
    """Information matrices (K, 3, 3) from box uncertainties (K, 3) = (sigma_x m, sigma_y m,
    sigma_yaw rad) given in the agent frame.

    diag(1/sx^2, 1/sy^2, 1/syaw^2), with the xy block rotated into the box frame in
    which the pose-graph residual lives (``R^T Omega R``; a no-op when sx == sy).
    Non-finite sigmas take ``default``; sigmas below the floors are raised to them
    (so zero uncertainty cannot produce infinite information).
    """
    sigma = np.asarray(uncertainty, dtype=float).reshape(-1, 3).copy()
    bad = ~np.isfinite(sigma)
    sigma[bad] = np.broadcast_to(np.asarray(default, dtype=float), sigma.shape)[bad]
    sigma = np.maximum(sigma, [floor_xy, floor_xy, floor_yaw])
    inv = 1.0 / sigma**2
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    info = np.zeros((sigma.shape[0], 3, 3))
    # R^T diag(a, b) R with R = [[c, -s], [s, c]].
    info[:, 0, 0] = c * c * inv[:, 0] + s * s * inv[:, 1]
    info[:, 1, 1] = s * s * inv[:, 0] + c * c * inv[:, 1]
    info[:, 0, 1] = info[:, 1, 0] = c * s * (inv[:, 1] - inv[:, 0])
    info[:, 2, 2] = inv[:, 2]
    return info


def prepare_inputs(
    ego_boxes: np.ndarray,
    ego_unc: np.ndarray,
    collab_boxes: Sequence[np.ndarray],
    collab_unc: Sequence[np.ndarray],
    reported: np.ndarray,
    params: UncertaintyParams,
) -> AlignmentInputs:
    """Validate the array call and compute box poses + information per agent.

    Raises ValueError naming the offending argument (shape, NaN boxes, list lengths).
    NaN/zero uncertainties are allowed (see :func:`box_information`).
    """
    reported = np.asarray(reported, dtype=float)
    if reported.size == 0:
        reported = reported.reshape(0, 3)
    if reported.ndim != 2 or reported.shape[1] != 3:
        raise ValueError(f"reported must have shape (N, 3) = (x, y, yaw); got {reported.shape}")
    if not np.all(np.isfinite(reported)):
        raise ValueError("reported contains NaN or inf; all values must be finite")
    n = reported.shape[0]
    if len(collab_boxes) != n or len(collab_unc) != n:
        raise ValueError(
            f"collab_boxes and collab_unc must have one entry per reported pose ({n}); "
            f"got {len(collab_boxes)} and {len(collab_unc)}"
        )
    all_boxes, all_unc = [], []
    pairs = zip([ego_boxes, *collab_boxes], [ego_unc, *collab_unc], strict=True)
    for agent, (boxes, unc) in enumerate(pairs):
        name = "ego" if agent == 0 else f"collab[{agent - 1}]"
        boxes = validate_boxes(boxes, f"{name} boxes")
        unc = np.asarray(unc, dtype=float)
        if unc.size == 0:
            unc = unc.reshape(0, 3)
        if unc.shape != (boxes.shape[0], 3):
            raise ValueError(
                f"{name} uncertainty must have shape ({boxes.shape[0]}, 3) = "
                f"(sigma_x, sigma_y, sigma_yaw); got {unc.shape}"
            )
        all_boxes.append(boxes)
        all_unc.append(unc)
    # One vectorised pass over every agent's boxes (per-agent calls cost more in overhead).
    poses = np.concatenate(all_boxes)[:, [0, 1, 6]]
    information = box_information(
        poses,
        np.concatenate(all_unc),
        params.sigma_floor_xy,
        params.sigma_floor_yaw,
        params.default_sigma,
    )
    offsets = np.cumsum([0] + [b.shape[0] for b in all_boxes])
    return AlignmentInputs(
        split_rows(poses, offsets),
        split_rows(information, offsets),
        reported,
        poses,
        information,
        offsets,
    )


def prior_information(sigma_t: float, sigma_r: float) -> np.ndarray:
    """diag(1/sigma_t^2, 1/sigma_t^2, 1/sigma_r^2) for an agent-agent prior (m, rad)."""
    return np.diag([sigma_t**-2, sigma_t**-2, sigma_r**-2])


def landmark_graph(
    inputs: AlignmentInputs,
    agent_ids: np.ndarray,
    agents: np.ndarray,
    landmarks: np.ndarray,
    obs_agent: np.ndarray,
    obs_box: np.ndarray,
    obs_landmark: np.ndarray,
    prior_info: np.ndarray | None = None,
) -> PoseGraph:
    """Pose graph of some agents and landmarks with one edge per box observation.

    agent_ids (A,): sorted agent indices in the graph, the ego (0) first, so the ego is
    vertex 0; agents (A, 3) and landmarks (L, 3) are their initial poses in the ego
    frame. Observation o says box ``obs_box[o]`` of agent ``obs_agent[o]`` (an agent
    index, not a vertex index) sees landmark vertex ``obs_landmark[o]``.
    prior_info (3, 3): when given, every non-ego agent gets an ego -> agent prior edge
    measured by its reported pose.
    """
    if agent_ids.size == 0 or agent_ids[0] != 0:
        raise ValueError(f"agent_ids must start with the ego (0); got {agent_ids}")
    rows = inputs.offsets[obs_agent] + obs_box
    meas, info = inputs.all_poses[rows], inputs.all_information[rows]
    others = agent_ids[1:] if prior_info is not None else agent_ids[:0]
    return PoseGraph.build(
        agents,
        landmarks,
        np.searchsorted(agent_ids, obs_agent),
        obs_landmark,
        meas,
        info,
        prior_from=np.zeros(others.size, dtype=np.int64),
        prior_to=np.arange(1, others.size + 1),
        prior_measurement=inputs.reported[others - 1],
        prior_information=np.broadcast_to(prior_info, (others.size, 3, 3)) if others.size else None,
    )


def pairs_from_observations(
    obs_agent: np.ndarray, obs_box: np.ndarray, obs_landmark: np.ndarray
) -> np.ndarray:
    """``matched_pairs`` rows (slot_a, box_a, slot_b, box_b) for every two observations of
    the same landmark by different agents (slot -1 = ego), ordered by landmark then agent."""
    order = np.lexsort((obs_box, obs_agent, obs_landmark))
    agent, box, land = obs_agent[order], obs_box[order], obs_landmark[order]
    index = np.arange(land.size)
    firsts, seconds = [np.zeros(0, dtype=np.int64)], [np.zeros(0, dtype=np.int64)]
    offset = 1
    # Observations of one landmark are contiguous: pair each with the next ones.
    while offset < land.size and np.any(land[offset:] == land[:-offset]):
        same = (land[offset:] == land[:-offset]) & (agent[offset:] != agent[:-offset])
        firsts.append(index[:-offset][same])
        seconds.append(index[offset:][same])
        offset += 1
    first, second = np.concatenate(firsts), np.concatenate(seconds)
    order2 = np.lexsort((second, first))
    first, second = first[order2], second[order2]
    return np.stack([agent[first] - 1, box[first], agent[second] - 1, box[second]], axis=1).astype(
        np.int64
    )


def params_from_kwargs(cls: type, kwargs: dict, method: str):
    """The parameter dataclass ``cls`` built from keyword arguments by
    :func:`~roco_env.schema.build` (every value checked against its field's spec); an
    unknown name raises ValueError listing the accepted ones. ``method`` names the policy in
    the messages.

    The one cache of checked parameters: aligners are called every frame with the same
    keywords, and the checks read the class's annotations (about a millisecond a build:
    docs/performance.md). It keys on the
    class, ``method`` and each keyword's name, type and value: the type because equal values
    of other types (``1``, ``1.0``, ``True``) hash alike but check differently. The
    parameter classes are frozen, so one instance serves every call with those keywords;
    an unhashable value (a list) is checked on every call.
    """
    try:
        key = tuple(sorted((name, type(value), value) for name, value in kwargs.items()))
        hash(key)
    except TypeError:  # an unhashable value: build without the cache
        return _build_params(cls, kwargs, method)
    return _cached_params(cls, key, method)


@functools.lru_cache(maxsize=256)
def _cached_params(cls: type, key: tuple, method: str):
    return _build_params(cls, {name: value for name, _, value in key}, method)


def _build_params(cls: type, kwargs: dict, method: str):
    allowed = sorted(cls.__dataclass_fields__)
    unknown = sorted(set(kwargs) - set(allowed))
    if unknown:
        raise ValueError(f"unknown {method} parameter(s) {unknown}; allowed: {', '.join(allowed)}")
    return build(cls, kwargs, where=method)
