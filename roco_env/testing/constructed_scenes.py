"""Constructed alignment scenes with known pose errors (tests and benchmarks only).

Objects are boxes in a world frame, agents sit at true poses and see the objects
within their sensor range, boxes are expressed in each agent's true frame, and
each collaborator's reported pose is its true pose perturbed by a known error.
The ego (agent 0) reports its true pose, so the ego frame is the world seen from
the ego and the true relative poses are exact.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from roco_env.geometry import se2_compose, se2_inverse, se2_relative, transform_boxes

__all__ = [
    "AlignmentScene",
    "benchmark_scene",
    "lattice_scene",
    "make_scene",
    "parking_rows",
    "pose_error",
    "random_objects",
    "to_observation",
]


@dataclass(frozen=True)
class AlignmentScene:
    """Inputs of an aligner plus the truth.

    ego_boxes (K0, 7), ego_unc (K0, 3), collab_boxes[j] (K_j, 7), collab_unc[j] (K_j, 3):
    boxes in each agent's own frame; reported / true (N, 3): reported and true T_{j->i};
    ego_ids (K0,), collab_ids[j] (K_j,): object index of each box.
    """

    ego_boxes: np.ndarray
    ego_unc: np.ndarray
    collab_boxes: list[np.ndarray]
    collab_unc: list[np.ndarray]
    reported: np.ndarray
    true: np.ndarray
    ego_ids: np.ndarray
    collab_ids: list[np.ndarray]

    def args(self) -> tuple:
        """Positional arguments of ``coalign_align`` / ``roco_align``."""
        return self.ego_boxes, self.ego_unc, self.collab_boxes, self.collab_unc, self.reported

    def padded_ids(self) -> tuple[np.ndarray, np.ndarray]:
        """(ego_ids (K,), collab_ids (N, K)) padded with -1, as the env's privileged info."""
        k = max([self.ego_ids.size, *[c.size for c in self.collab_ids]])
        ego = np.full(k, -1)
        ego[: self.ego_ids.size] = self.ego_ids
        collab = np.full((len(self.collab_ids), k), -1)
        for j, ids in enumerate(self.collab_ids):
            collab[j, : ids.size] = ids
        return ego, collab


def pose_error(translation: float, rotation_deg: float, direction_rad: float = 0.0) -> np.ndarray:
    """A pose error (dx, dy, dyaw) of the given size: metres along ``direction_rad``, degrees."""
    return np.array(
        [
            translation * np.cos(direction_rad),
            translation * np.sin(direction_rad),
            np.deg2rad(rotation_deg),
        ]
    )


def random_objects(
    rng: np.random.Generator, count: int, extent: float, min_gap: float = 6.0
) -> np.ndarray:
    """``count`` car boxes (M, 7) uniformly in [-extent, extent]^2 with random yaw and
    centres at least ``min_gap`` m apart where possible (rejection sampling, bounded tries)."""
    centres: list[np.ndarray] = []
    for _ in range(50 * count):
        if len(centres) == count:
            break
        c = rng.uniform(-extent, extent, size=2)
        if all(np.hypot(*(c - o)) >= min_gap for o in centres):
            centres.append(c)
    xy = np.array(centres).reshape(-1, 2)
    n = xy.shape[0]
    return np.column_stack(
        [
            xy,
            np.full(n, 0.8),
            np.full(n, 4.5),
            np.full(n, 1.9),
            np.full(n, 1.6),
            rng.uniform(-np.pi, np.pi, n),
        ]
    )


def parking_rows(
    rows: int,
    per_row: int,
    spacing: float = 2.5,
    row_gap: float = 7.0,
    origin: tuple[float, float] = (0.0, 0.0),
    occupancy: np.ndarray | None = None,
    jitter: tuple[float, float, float] = (0.0, 0.0, 0.0),
    reversed_share: float = 0.0,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Parked cars (M, 7) side by side: ``rows`` rows along x, ``spacing`` m apart,
    rows ``row_gap`` m apart, cars facing +y; ``occupancy`` (rows*per_row,) bool drops
    empty spots. Real cars sit imperfectly in their slots: ``jitter`` = std of the
    (x m, y m, yaw deg) offsets and ``reversed_share`` = share of cars parked facing -y
    (both drawn from ``rng``)."""
    gx, gy = np.meshgrid(np.arange(per_row) * spacing, np.arange(rows) * row_gap)
    xy = np.column_stack([gx.ravel() + origin[0], gy.ravel() + origin[1]])
    if occupancy is not None:
        xy = xy[np.asarray(occupancy, dtype=bool)]
    n = xy.shape[0]
    yaw = np.full(n, np.pi / 2)
    if any(jitter) or reversed_share > 0:
        if rng is None:
            raise ValueError("rng is required for jitter or reversed_share")
        xy = xy + rng.normal(0.0, jitter[:2], size=(n, 2))
        yaw = yaw + np.deg2rad(rng.normal(0.0, jitter[2], size=n))
        yaw = np.where(rng.random(n) < reversed_share, yaw - np.pi, yaw)
    return np.column_stack(
        [xy, np.full(n, 0.8), np.full(n, 4.5), np.full(n, 1.9), np.full(n, 1.6), yaw]
    )


def make_scene(
    objects: np.ndarray,
    agent_poses: np.ndarray,
    errors: np.ndarray,
    sensor_range: float = 70.0,
    sigma: tuple[float, float, float] = (0.1, 0.1, 0.02),
    noise: tuple[float, float, float] | None = None,
    rng: np.random.Generator | None = None,
) -> AlignmentScene:
    """Build a scene: agent 0 is the ego; errors (N, 3) perturb the collaborators' world
    poses (reported_j = true_j + error_j, yaw in rad).

    sigma: the uncertainty every box reports; noise: std of Gaussian noise added to the
    boxes' (x, y, yaw) in the agent frame (needs ``rng``); None = exact boxes.
    """
    agent_poses = np.asarray(agent_poses, dtype=float)
    errors = np.asarray(errors, dtype=float).reshape(-1, 3)
    if errors.shape[0] != agent_poses.shape[0] - 1:
        raise ValueError(f"errors must have one row per collaborator; got {errors.shape}")
    per_agent, ids = [], []
    for pose in agent_poses:
        local = transform_boxes(objects, se2_inverse(pose))
        seen = np.nonzero(np.hypot(local[:, 0], local[:, 1]) <= sensor_range)[0]
        boxes = local[seen]
        if noise is not None:
            if rng is None:
                raise ValueError("rng is required when noise is given")
            boxes[:, [0, 1, 6]] += rng.normal(0.0, noise, size=(seen.size, 3))
            boxes[:, 6] = np.mod(boxes[:, 6] + np.pi, 2 * np.pi) - np.pi
        per_agent.append(boxes)
        ids.append(seen)
    unc = [np.tile(np.asarray(sigma, dtype=float), (b.shape[0], 1)) for b in per_agent]
    noisy = se2_compose(agent_poses[1:], np.zeros(3)) + errors
    return AlignmentScene(
        ego_boxes=per_agent[0],
        ego_unc=unc[0],
        collab_boxes=per_agent[1:],
        collab_unc=unc[1:],
        reported=se2_relative(agent_poses[0], noisy),
        true=se2_relative(agent_poses[0], agent_poses[1:]),
        ego_ids=ids[0],
        collab_ids=ids[1:],
    )


def to_observation(scene: AlignmentScene, max_boxes: int, max_collaborators: int) -> dict:
    """The scene as one agent's env observation (contract layout, zero padding, masks).

    The ego's reported pose is the origin; boxes beyond ``max_boxes`` and collaborators
    beyond ``max_collaborators`` are dropped.
    """
    k, n = max_boxes, max_collaborators
    obs = {
        "pose": np.zeros(3, np.float32),
        "boxes": np.zeros((k, 7), np.float32),
        "uncertainty": np.zeros((k, 3), np.float32),
        "scores": np.zeros(k, np.float32),
        "box_mask": np.zeros(k, np.int8),
        "collab_mask": np.zeros(n, np.int8),
        "collab_poses": np.zeros((n, 3), np.float32),
        "collab_rel_poses": np.zeros((n, 3), np.float32),
        "collab_boxes": np.zeros((n, k, 7), np.float32),
        "collab_uncertainty": np.zeros((n, k, 3), np.float32),
        "collab_scores": np.zeros((n, k), np.float32),
        "collab_box_mask": np.zeros((n, k), np.int8),
    }
    m = min(k, scene.ego_boxes.shape[0])
    obs["boxes"][:m], obs["uncertainty"][:m] = scene.ego_boxes[:m], scene.ego_unc[:m]
    obs["scores"][:m], obs["box_mask"][:m] = 1.0, 1
    for j in range(min(n, len(scene.collab_boxes))):
        m = min(k, scene.collab_boxes[j].shape[0])
        obs["collab_mask"][j] = 1
        obs["collab_poses"][j] = obs["collab_rel_poses"][j] = scene.reported[j]
        obs["collab_boxes"][j, :m] = scene.collab_boxes[j][:m]
        obs["collab_uncertainty"][j, :m] = scene.collab_unc[j][:m]
        obs["collab_scores"][j, :m], obs["collab_box_mask"][j, :m] = 1.0, 1
    return obs


def benchmark_scene(
    rng: np.random.Generator,
    n_agents: int,
    n_objects: int,
    error_m: float = 0.8,
    error_deg: float = 0.8,
) -> AlignmentScene:
    """``n_objects`` cars spread over a square sized so they stay ~5 m apart, ``n_agents``
    agents within 25 m of the ego (all see nearly everything), realistic box noise
    (5 cm, 0.6 deg) and reported poses off by ``error_m`` / ``error_deg`` in random
    directions."""
    objects = random_objects(rng, n_objects, 8.0 * np.sqrt(n_objects), min_gap=5.0)
    angle = rng.uniform(-np.pi, np.pi, n_agents)
    radius = np.where(np.arange(n_agents) == 0, 0.0, rng.uniform(5.0, 25.0, n_agents))
    agents = np.column_stack(
        [radius * np.cos(angle), radius * np.sin(angle), rng.uniform(-np.pi, np.pi, n_agents)]
    )
    errors = np.array(
        [pose_error(error_m, error_deg, d) for d in rng.uniform(-np.pi, np.pi, n_agents - 1)]
    ).reshape(-1, 3)
    return make_scene(objects, agents, errors, noise=(0.05, 0.05, 0.01), rng=rng)


def lattice_scene(
    rng: np.random.Generator, pitch: float, error_m: float, error_deg: float
) -> AlignmentScene:
    """A periodic lattice: identical cars ``pitch`` m apart in 2-6 rows 7 m apart, 40-160 m
    long, placed exactly or with 5 cm / 1 deg jitter (even odds); the ego and one
    collaborator in aisles between the rows (up to 30 m apart along them, any heading),
    sensor range 40-70 m, realistic box noise (5 cm, 0.6 deg); the collaborator's reported
    pose off by Gaussian errors of std ``error_m`` (m, x and y each) and ``error_deg`` (deg).
    Every draw from ``rng``."""
    rows = int(rng.integers(2, 7))
    length = rng.uniform(40.0, 160.0)
    per_row = max(int(length / pitch), 2)
    jitter = (0.05, 0.05, 1.0) if rng.random() < 0.5 else (0.0, 0.0, 0.0)
    objects = parking_rows(rows, per_row, spacing=pitch, origin=(-0.5 * per_row * pitch, 0.0),
                           jitter=jitter, rng=rng)
    aisles = (rng.integers(0, rows - 1, size=2) + 0.5) * 7.0
    along = rng.uniform(-0.4, 0.4) * length + np.array([0.0, rng.uniform(-30.0, 30.0)])
    agents = np.column_stack([along, aisles, rng.uniform(-np.pi, np.pi, 2)])
    error = np.array([*rng.normal(0.0, error_m, 2), np.deg2rad(rng.normal(0.0, error_deg))])
    return make_scene(objects, agents, [error], sensor_range=rng.uniform(40.0, 70.0),
                      noise=(0.05, 0.05, 0.01), rng=rng)
