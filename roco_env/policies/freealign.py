"""FreeAlign (Lei et al., ICRA 2024, arXiv 2405.02965), re-implemented without its GNN.

FreeAlign registers two agents by finding the largest common subgraph of their
*salient-object graphs*: one node per detected box, fully connected, each edge
carrying the distance between the two box centres (the relative distance matrix
R[p, q] of the paper; distances are invariant to the unknown relative pose).

1. **Node similarity.** The paper learns node embeddings from the distance matrix
   with an edge-feature graph attention network (EdgeGAT) trained on the dataset. We
   have no trained network here and use the features it is derived from: each node's
   distances to its ``descriptor_neighbors`` nearest nodes, sorted; nodes i (ego) and
   k (collaborator) are similar by how many of these distances find a partner,
   sim(i, k) = sum_a [min_b |d_i^a - d_k^b| <= ``edge_tolerance``].
   The name ``freealign`` in this package means this distance-matrix variant.
2. **Mass-based multi-anchor subgraph search (MASS).** The ``anchors`` most similar
   node pairs each seed a common subgraph; the seed grows greedily by node pairs
   (m, n) in order of edge agreement with the current subgraph, a pair being added
   only when its distances to *every* node already in the subgraph agree within
   ``edge_tolerance`` m (every accepted node is an anchor for the next ones) and,
   with ``edge_yaw_tolerance_deg`` set, its heading relative to the seed agrees
   within that many degrees modulo pi (an extra edge feature the boxes carry;
   None = distances only, as the paper's graph). The subgraph with the largest mass
   (node count) wins; the others, ordered by mass, are alternatives. Growth stops at
   ``max_subgraph`` nodes (our choice, for speed: 16 consistent nodes already pin the
   pose for the refinement, which re-associates every box, and a wrong anchor rarely
   gathers that many; None grows each subgraph to the end, as the paper).
3. **Robust transform.** The SVD (Kabsch) fit on the common subgraph's centres gives
   the relative pose; the shared refinement (re-association + SVD, robust least
   squares) and do-no-harm rule of :mod:`roco_env.policies.prior_free` follow.
   A distance-preserving match can be a mirror image; the proper-rotation fit of a
   mirrored subgraph explains few boxes and loses the consensus.

FreeAlign also estimates the time offset between agents; the env delivers messages
of the same step, so only the spatial part is implemented.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.distance import cdist

from roco_env.policies.prior_free import (
    PriorFreeParams,
    PriorFreePolicy,
    Proposer,
    aligner,
    distinct_top,
    fit_se2,
)
from roco_env.policies.prior_free_kernels import (
    Gates,
    NodeGraph,
    descriptor_similarity,
    grow_subgraph,
)
from roco_env.schema import spec

__all__ = ["FreeAlignParams", "FreeAlignPolicy", "common_subgraph", "freealign_align",
           "freealign_search"]


@dataclass(frozen=True)
class FreeAlignParams(PriorFreeParams):
    """FreeAlign parameters on top of :class:`PriorFreeParams` (module docstring)."""

    descriptor_neighbors: int = spec(6, low=1, doc="nearest-node distances in a "
                                     "node's descriptor")
    edge_tolerance: float = spec(0.8, low=0.0, low_open=True,
                                 doc="two edges agree within this length difference, m")
    anchors: int = spec(4, low=1, doc="most similar node pairs, each "
                        "seeding a subgraph")
    edge_yaw_tolerance_deg: float | None = spec(15.0, low=0.0, high=90.0, low_open=True,
                                                high_open=True,
                                                doc="two edges agree within this heading "
                                                "difference, deg (None: distances only)")
    min_subgraph: int = spec(3, low=2, doc="nodes a subgraph needs to become a candidate "
                             "(2: an SE(2) fit)")
    max_subgraph: int | None = spec(16, doc="growth stops there (>= min_subgraph; None: grow "
                                    "to the full common subgraph)")

    def __post_init__(self) -> None:
        """The rule joining fields (each field's own: its spec)."""
        PriorFreeParams.__post_init__(self)
        if self.max_subgraph is not None and not self.max_subgraph >= self.min_subgraph:
            raise ValueError(f"max_subgraph must be None or >= min_subgraph="
                             f"{self.min_subgraph}; got {self.max_subgraph}")


def _descriptors(distances: np.ndarray, count: int) -> np.ndarray:
    """Each node's ``count`` smallest distances to other nodes, sorted (K, n), padded
    with NaN (which never matches) where a graph has fewer nodes."""
    k = distances.shape[0]
    n = min(count, k - 1)
    out = np.full((k, count), np.nan)
    if n > 0:
        masked = distances + np.diag(np.full(k, np.inf))
        out[:, :n] = np.sort(np.partition(masked, n - 1, axis=1)[:, :n], axis=1)
    return out


def _node_similarity(ego_d: np.ndarray, own_d: np.ndarray, tol: float) -> np.ndarray:
    """sim (M, K): how many of node i's descriptor distances find a distance of node k
    within ``tol`` m (padding never matches); compared in float32."""
    return descriptor_similarity(ego_d.astype(np.float32), own_d.astype(np.float32),
                                 np.float32(tol))


def common_subgraph(ego_d: np.ndarray, own_d: np.ndarray, seed: tuple[int, int],
                    tol: float, headings: tuple[np.ndarray, np.ndarray, float] | None = None,
                    max_nodes: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Grow the common subgraph of two distance matrices (M, M), (K, K) from ``seed``.

    Candidate node pairs are those whose distances to the seed agree within ``tol`` m,
    taken in order of that agreement; one joins when its distances to every node
    already in the subgraph agree within ``tol`` and it reuses neither box.
    headings (ego yaw (M,), own yaw (K,), tolerance rad), optional: a pair must also
    have headings relative to the seed's that agree within the tolerance modulo pi;
    max_nodes: stop growing at this many nodes (None = until no pair agrees).
    Returns the matched (ego nodes, own nodes), seed first.
    """
    ego_yaw, own_yaw, yaw_tol = headings if headings is not None else (
        np.zeros(ego_d.shape[0]), np.zeros(own_d.shape[0]), -1.0)
    ego = NodeGraph(np.ascontiguousarray(ego_d, dtype=float),
                    np.ascontiguousarray(ego_yaw, dtype=float))
    own = NodeGraph(np.ascontiguousarray(own_d, dtype=float),
                    np.ascontiguousarray(own_yaw, dtype=float))
    return grow_subgraph(tuple(ego), tuple(own), (int(seed[0]), int(seed[1])),
                         tuple(Gates(float(tol), float(yaw_tol))),
                         -1 if max_nodes is None else int(max_nodes))


def freealign_search(ego_boxes: np.ndarray, p: FreeAlignParams) -> Proposer:
    """The FreeAlign proposer for ego boxes (M, 7): collaborator boxes (K, 7) -> candidate
    T_{j->i} (H, 3), largest common subgraph first. The ego's graph is built once."""
    ego = ego_boxes[:, [0, 1, 6]]
    ego_d = cdist(ego[:, :2], ego[:, :2])
    ego_desc = _descriptors(ego_d, p.descriptor_neighbors)

    def propose(own_boxes: np.ndarray) -> np.ndarray:
        own = own_boxes[:, [0, 1, 6]]
        own_d = cdist(own[:, :2], own[:, :2])
        # Headings relative to the seed's are pose invariant (modulo pi).
        headings = None if p.edge_yaw_tolerance_deg is None else (
            ego[:, 2], own[:, 2], float(np.deg2rad(p.edge_yaw_tolerance_deg)))
        sim = _node_similarity(ego_desc, _descriptors(own_d, p.descriptor_neighbors),
                               p.edge_tolerance)
        count = min(int(p.anchors), sim.size)
        seeds = np.argsort(-sim, axis=None, kind="stable")[:count]
        found: list[tuple[int, np.ndarray]] = []
        for seed in seeds:
            i, k = np.unravel_index(seed, sim.shape)
            nodes_e, nodes_o = common_subgraph(ego_d, own_d, (int(i), int(k)),
                                               p.edge_tolerance, headings, p.max_subgraph)
            if nodes_e.size >= p.min_subgraph:
                found.append((nodes_e.size, fit_se2(own[nodes_o, :2], ego[nodes_e, :2])))
        if not found:
            return np.zeros((0, 3))
        mass = np.array([m for m, _ in found], dtype=float)
        poses = np.array([pose for _, pose in found])
        top = distinct_top(poses, mass, p.max_candidates, p)
        return poses[top]

    return propose


freealign_align = aligner(freealign_search, FreeAlignParams, "freealign",
                          "Correct the collaborators' relative poses with FreeAlign "
                          "(distance-matrix node features instead of the learned GNN).")


class FreeAlignPolicy(PriorFreePolicy):
    """FreeAlign as an env policy: ``FreeAlignPolicy(**params)(obs) -> action (N, 3)``."""

    ALIGN = staticmethod(freealign_align)
    PARAMS = FreeAlignParams
    METHOD = "freealign"
