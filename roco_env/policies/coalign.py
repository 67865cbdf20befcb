"""CoAlign's box alignment as its released code behaves (docs/alignment.md).

:func:`coalign_align` works on plain arrays in the ego's reported frame (ego =
identity; metres, radians), which equals CoAlign's "world under the noisy poses"
up to one rigid motion, so distances and yaw spreads are the same:

1. map every box into the ego frame with the reported poses;
2. greedy clustering in index order (ego boxes first, then slot 0, 1, ...): an
   unassigned seed takes every unassigned box of *another* agent whose centre is
   within ``cluster_threshold`` of the seed (not transitive, several boxes of one
   agent allowed); a cluster with >= 2 boxes is a landmark;
3. a landmark whose yaw variance (rad^2) exceeds ``hard_yaw_variance`` is "hard"
   and its edges are dropped; with <= ``max_landmarks_keep_prior`` landmarks, or a
   hard share >= ``max_hard_fraction``, every reported pose is kept. The variance
   is ``yaw_variance``:

   * ``"circular"`` (default, a deliberate deviation): the mean squared wrapped
     deviation from the circular mean, which does not depend on the frame and
     sees two boxes at +179 and -179 deg as 2 deg apart;
   * ``"released"``: what the released code computes, ``np.var`` of the boxes'
     yaws in the world frame (wrapped to [-pi, pi)), so a landmark whose yaws
     straddle +-pi is "hard" and the verdict depends on the world frame's
     orientation. The world frame is the ego's reported world pose: the array
     call takes its yaw as ``ego_yaw``; :class:`CoAlignPolicy` reads it from
     ``obs["pose"]``. Measured against the released code on identical inputs,
     the circular variance gives its corrected pose (within 1 cm) for 61% of the
     collaborators, the released variance for 97%;
4. pose graph: agents at their reported poses with the ego fixed, landmarks at their
   seed box, one edge per clustered box with information diag(1/sx^2, 1/sy^2,
   1/syaw^2) from its uncertainty, no robust kernel, Levenberg-Marquardt (cap
   ``max_solver_iterations``).

An agent keeps its reported pose (applied=False) when it has fewer than
``min_matches`` boxes on easy landmarks (default 1: "no shared landmark", the
released behaviour) or is not connected to the ego through landmarks (no chain
agent - landmark - agent ... reaches the ego): it is left out of the pose graph,
the others are still optimised, and ``reason`` names its slots ("slots [k]: no
landmark path to the ego").
``matched_pairs`` lists the box pairs of the easy landmarks, also when the rule
of step 3 keeps the priors.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from roco_env.geometry import se2_compose, wrap_angle
from roco_env.policies.adapter import ArrayAlignmentPolicy, ObservationView
from roco_env.policies.base import AlignmentResult
from roco_env.policies.landmarks import (
    UncertaintyParams,
    landmark_graph,
    pairs_from_observations,
    params_from_kwargs,
    prepare_inputs,
)
from roco_env.policies.posegraph import optimize
from roco_env.schema import spec

__all__ = [
    "CoAlignParams",
    "CoAlignPolicy",
    "coalign_align",
    "greedy_clusters",
    "circular_variance",
    "YAW_VARIANCES",
]

YAW_VARIANCES = ("circular", "released")


@dataclass(frozen=True)
class CoAlignParams(UncertaintyParams):
    """CoAlign parameters (module docstring)."""

    cluster_threshold: float = spec(1.5, low=0.0, low_open=True,
                                    doc="a seed box takes the boxes within this distance, m")
    hard_yaw_variance: float = spec(0.2, low=0.0, low_open=True,
                                    doc="a landmark with a larger yaw variance (rad^2) is hard")
    max_landmarks_keep_prior: int = spec(3, low=0, doc="with at most this many landmarks "
                                         "every reported pose is kept")
    max_hard_fraction: float = spec(0.5, low=0.0, high=1.0, low_open=True,
                                    doc="with this share of hard landmarks or more every "
                                    "reported pose is kept")
    min_matches: int = spec(1, low=1, doc="boxes on easy landmarks a collaborator needs")
    max_solver_iterations: int = spec(1000, low=1, doc="Levenberg-Marquardt cap")
    yaw_variance: str = spec("circular", choices=YAW_VARIANCES,
                             doc="a landmark's yaw variance: circular, or the released "
                             "code's np.var in the world frame")


def greedy_clusters(xy: np.ndarray, owner: np.ndarray, threshold: float) -> list[np.ndarray]:
    """CoAlign's greedy clustering of box centres xy (B, 2) owned by agents owner (B,).

    Returns the clusters with >= 2 boxes (index arrays, seed first). Boxes of the seed's
    own agent never join its cluster.
    """
    neighbours, start = _close_pairs(xy, owner, threshold)
    assigned = np.zeros(xy.shape[0], dtype=bool)
    clusters = []
    # Only boxes with a close box of another agent can seed a cluster of >= 2.
    for seed in np.nonzero(np.diff(start))[0]:
        if assigned[seed]:
            continue
        close = neighbours[start[seed] : start[seed + 1]]
        members = close[~assigned[close]]
        assigned[seed] = True
        if members.size:
            assigned[members] = True
            clusters.append(np.concatenate([[seed], members]))
    return clusters


def _close_pairs(
    xy: np.ndarray, owner: np.ndarray, threshold: float
) -> tuple[np.ndarray, np.ndarray]:
    """Boxes of other agents within ``threshold`` of each box, as CSR lists: the neighbours
    of box b are ``neighbours[start[b]:start[b + 1]]`` in increasing index order.

    A k-d tree finds the close pairs without the dense (B, B) distance matrix.
    """
    pairs = cKDTree(xy).query_pairs(threshold, output_type="ndarray").reshape(-1, 2)
    pairs = pairs[owner[pairs[:, 0]] != owner[pairs[:, 1]]]
    source = np.concatenate([pairs[:, 0], pairs[:, 1]])
    target = np.concatenate([pairs[:, 1], pairs[:, 0]])
    order = np.lexsort((target, source))
    start = np.concatenate([[0], np.cumsum(np.bincount(source, minlength=xy.shape[0]))])
    return target[order], start


def circular_variance(yaw: np.ndarray) -> float:
    """Mean squared wrapped deviation (rad^2) of angles from their circular mean."""
    yaw = np.asarray(yaw, dtype=float)
    return float(_circular_variances(yaw, np.zeros(yaw.size, dtype=np.int64), 1)[0])


def _circular_variances(yaw: np.ndarray, label: np.ndarray, count: int) -> np.ndarray:
    """:func:`circular_variance` of each group of angles (group ``label`` in [0, count))."""
    size = np.bincount(label, minlength=count)
    mean = np.arctan2(
        np.bincount(label, np.sin(yaw), count) / size,
        np.bincount(label, np.cos(yaw), count) / size,
    )
    return np.bincount(label, wrap_angle(yaw - mean[label]) ** 2, count) / size


def _released_variances(yaw: np.ndarray, label: np.ndarray, count: int) -> np.ndarray:
    """``np.var`` of each group's yaws as given (no wrap-around), the released rule."""
    size = np.bincount(label, minlength=count)
    mean = np.bincount(label, yaw, count) / size
    return np.bincount(label, (yaw - mean[label]) ** 2, count) / size


def coalign_align(
    ego_boxes: np.ndarray,
    ego_unc: np.ndarray,
    collab_boxes: Sequence[np.ndarray],
    collab_unc: Sequence[np.ndarray],
    reported: np.ndarray,
    *,
    ego_yaw: float = 0.0,
    **params,
) -> AlignmentResult:
    """Correct the collaborators' relative poses as released CoAlign does.

    Same array call as :func:`roco_env.policies.roco.roco_align`; params: fields of
    :class:`CoAlignParams`. ego_yaw: the ego's reported world yaw (rad), used only by
    ``yaw_variance="released"`` (box yaws are taken in the world frame there).
    """
    p = params_from_kwargs(CoAlignParams, params, "coalign")
    inputs = prepare_inputs(ego_boxes, ego_unc, collab_boxes, collab_unc, reported, p)
    n = inputs.n_collaborators
    agent_poses = np.vstack([np.zeros((1, 3)), inputs.reported])
    owner = np.repeat(np.arange(n + 1), np.diff(inputs.offsets))
    box = np.arange(owner.size) - inputs.offsets[owner]
    world = se2_compose(agent_poses[owner], inputs.all_poses).reshape(-1, 3)
    clusters = greedy_clusters(world[:, :2], owner, p.cluster_threshold)
    members = np.concatenate(clusters) if clusters else np.zeros(0, dtype=np.int64)
    label = np.repeat(np.arange(len(clusters)), [c.size for c in clusters])
    if p.yaw_variance == "circular":
        spread = _circular_variances(world[members, 2], label, len(clusters))
    else:
        spread = _released_variances(wrap_angle(world[members, 2] + float(ego_yaw)), label,
                                     len(clusters))
    easy = [c for c, v in zip(clusters, spread, strict=True) if v <= p.hard_yaw_variance]
    obs = np.concatenate([c for c in easy]) if easy else np.zeros(0, dtype=np.int64)
    obs_land = np.concatenate([np.full(c.size, k) for k, c in enumerate(easy)]) if easy else obs
    result = AlignmentResult(
        corrected=inputs.reported.copy(),
        applied=np.zeros(n, dtype=bool),
        matched_pairs=pairs_from_observations(owner[obs], box[obs], obs_land),
        landmarks=world[[c[0] for c in easy]].reshape(-1, 3),
    )
    n_hard = len(clusters) - len(easy)
    if len(clusters) <= p.max_landmarks_keep_prior:
        result.reason = f"{len(clusters)} landmarks <= {p.max_landmarks_keep_prior}"
        return result
    if n_hard >= p.max_hard_fraction * len(clusters):
        result.reason = f"{n_hard} of {len(clusters)} landmarks are hard"
        return result
    agent_ids = _usable_agents(owner[obs], obs_land, n + 1, p.min_matches)
    if agent_ids.size == 1:
        result.reason = "no collaborator shares a landmark with the ego"
        return result
    keep = np.isin(owner[obs], agent_ids)
    kept_land, obs_land = np.unique(obs_land[keep], return_inverse=True)
    graph = landmark_graph(
        inputs,
        agent_ids,
        agent_poses[agent_ids],
        result.landmarks[kept_land],
        owner[obs][keep],
        box[obs][keep],
        obs_land,
    )
    solution = optimize(graph, fixed=0, kernel=None, max_iterations=p.max_solver_iterations)
    result.corrected[agent_ids[1:] - 1] = solution.agents[1:]
    result.applied[agent_ids[1:] - 1] = True
    result.landmarks = solution.landmarks
    result.outer_iterations, result.solver_iterations = 1, solution.iterations
    missing = sorted(set(range(n)) - set(agent_ids[1:] - 1))
    if missing:
        result.reason = f"slots {missing}: no landmark path to the ego"
    return result


def _usable_agents(
    obs_agent: np.ndarray, obs_land: np.ndarray, n_agents: int, min_matches: int
) -> np.ndarray:
    """Agents (sorted, ego first) with >= min_matches observations, connected to the ego
    through landmarks they share."""
    counts = np.bincount(obs_agent, minlength=n_agents)
    ok = (counts >= min_matches) | (np.arange(n_agents) == 0)
    sel = ok[obs_agent]
    n_land = int(obs_land.max(initial=-1)) + 1
    # Bipartite agent-landmark graph: vertices 0..n_agents-1 agents, then landmarks.
    adjacency = coo_matrix(
        (np.ones(int(sel.sum())), (obs_agent[sel], n_agents + obs_land[sel])),
        shape=(n_agents + n_land, n_agents + n_land),
    )
    _, label = connected_components(adjacency, directed=False)
    return np.nonzero(ok & (label[:n_agents] == label[0]))[0]


class CoAlignPolicy(ArrayAlignmentPolicy):
    """CoAlign as an env policy: ``CoAlignPolicy(**params)(obs, info=None) -> action (N, 3)``."""

    def __init__(self, **params) -> None:
        super().__init__(
            coalign_align, params_from_kwargs(CoAlignParams, params, "coalign"), params
        )

    def align_view(
        self, view: ObservationView, observation: dict, info: dict | None
    ) -> AlignmentResult:
        # The released yaw variance is taken in the world frame: the ego's reported yaw.
        if self.params.yaw_variance == "released":
            return self._align(*view.arrays, **self._kwargs,
                               ego_yaw=float(observation["pose"][2]))
        return super().align_view(view, observation, info)
