"""Training and validation scenes for the learned detector, drawn from the scenario library.

A scene is one frame of a synthetic scenario: every agent's sampled LiDAR
raster, the boxes it must find (objects with at least one of its sampled
points, in its true frame), for every agent as an ego the boxes its
collaboration must find (points from any member), its collaborators (the
environment's rule: within communication range, at most ``max_collaborators``)
and their true relative poses T_{j->i}. It also keeps the evaluation ground
truth (the environment's: objects visible to the agent, or to any member of the
collaboration, inside the scenario's evaluation range) so validation AP is
computed exactly as the environment computes it.

Seeds: scene ``k`` of a split is drawn from ``np.random.default_rng((base, k))``
with base :data:`TRAIN_SEED_BASE` or :data:`VALIDATION_SEED_BASE`; both are at
or above 10**6, so they never meet the small seeds (0, 1, 2, ...) used to
evaluate the environment, whose generators are also built differently.
"""

from __future__ import annotations

import multiprocessing
from dataclasses import dataclass
from functools import partial

import numpy as np

from roco_env.evaluation import ground_truths
from roco_env.geometry import se2_inverse, se2_relative, transform_boxes
from roco_env.scenario import ScenarioConfig, load_scenario
from roco_env.sensing.bev_grid import BevGrid
from roco_env.sensing.lidar import (
    LIDAR_CHANNELS,
    ScanNoise,
    ground_references,
    lidar_rasters,
    sample_scans,
)
from roco_env.sensing.messages import select_collaborators
from roco_env.sensing.visibility import compute_visibility
from roco_env.traffic import make_traffic_source

__all__ = ["TRAIN_SCENARIOS", "TRAIN_SEED_BASE", "VALIDATION_SEED_BASE", "WORKER_CONTEXT", "Scene",
           "make_scenes"]

# Worker processes (scene generation, training batches) are forked: they share the
# scenes with the parent without copying or pickling them (Linux; elsewhere use 0 workers).
WORKER_CONTEXT = "fork"
TRAIN_SEED_BASE = 1_000_000
VALIDATION_SEED_BASE = 2_000_000
# The synthetic scenarios of the library (replay and highway-env sources need external data).
TRAIN_SCENARIOS = ("urban_intersection", "crowded_intersection", "highway_dense",
                   "urban_roundabout", "parking_lot", "traffic_jam", "v2x_crossroad")
# A scene is taken after a random number of traffic steps in [0, _MAX_WARMUP).
_MAX_WARMUP = 40


@dataclass(frozen=True)
class Scene:
    """One frame of A agents (see the module docstring); boxes (K, 7) in agent frames.

    rasters (A, C, H, W) float32; targets[a]: boxes agent a must find;
    group_targets[a]: boxes a's collaboration must find; collaborators[a]:
    agent indices; relative[a] (n_a, 3) true T_{j->a}; eval_gt[a] / group_eval_gt[a]:
    the environment's single-agent / collaboration ground truth; grounds (A,)
    ground reference heights (m); scenario: its name.
    """

    rasters: np.ndarray
    targets: tuple[np.ndarray, ...]
    group_targets: tuple[np.ndarray, ...]
    collaborators: tuple[tuple[int, ...], ...]
    relative: tuple[np.ndarray, ...]
    eval_gt: tuple[np.ndarray, ...]
    group_eval_gt: tuple[np.ndarray, ...]
    grounds: np.ndarray
    scenario: str


def _scene(config: ScenarioConfig, grid: BevGrid, noise: ScanNoise,
           rng: np.random.Generator) -> Scene:
    source = make_traffic_source(config)
    state = source.reset(rng)
    for _ in range(int(rng.integers(_MAX_WARMUP))):
        state = source.step(config.traffic.dt)
    visibility = compute_visibility(state)
    scans = sample_scans(state, visibility, noise, rng)
    n = state.num_agents
    rasters = lidar_rasters(scans, visibility.ray_ranges, grid) if n else np.zeros(
        (0, len(LIDAR_CHANNELS), grid.H, grid.W))
    seen = np.zeros((n, state.num_objects), dtype=bool)
    for a, scan in enumerate(scans):
        seen[a, scan.obj[scan.obj >= 0]] = True
    collaborators = tuple(tuple(select_collaborators(state, a, config.max_collaborators))
                          for a in range(n))
    boxes = np.asarray(state.object_boxes, dtype=float).reshape(-1, 7)

    def in_frame(a: int, objects: np.ndarray) -> np.ndarray:
        return transform_boxes(boxes[objects], se2_inverse(state.agent_poses[a]))

    ev = config.evaluation
    single = ground_truths(state, visibility.visible, [(a, ()) for a in range(n)],
                           ev.x_range, ev.y_range)
    group = ground_truths(state, visibility.visible, [(a, c) for a, c in
                                                      enumerate(collaborators)],
                          ev.x_range, ev.y_range)
    return Scene(
        rasters=rasters.astype(np.float32),
        targets=tuple(in_frame(a, np.flatnonzero(seen[a])) for a in range(n)),
        group_targets=tuple(in_frame(a, np.flatnonzero(seen[[a, *c]].any(axis=0)))
                            for a, c in enumerate(collaborators)),
        collaborators=collaborators,
        relative=tuple(se2_relative(np.repeat(state.agent_poses[a][None], len(c), axis=0),
                                    state.agent_poses[list(c)]).reshape(-1, 3)
                       for a, c in enumerate(collaborators)),
        eval_gt=tuple(b for b, _ in single),
        group_eval_gt=tuple(b for b, _ in group),
        grounds=ground_references(state),
        scenario=config.name,
    )


def _scene_at(job: tuple[ScenarioConfig, int, int, BevGrid, ScanNoise]) -> Scene:
    config, seed_base, k, grid, noise = job
    return _scene(config, grid, noise, np.random.default_rng((seed_base, k)))


def make_scenes(scenarios: tuple[str, ...], count: int, seed_base: int, grid: BevGrid,
                noise: ScanNoise, progress: bool = False, workers: int = 0) -> list[Scene]:
    """``count`` scenes cycling through ``scenarios``; scene k from rng((seed_base, k)).

    workers: processes generating them (0: this one); the scenes do not depend on it.
    """
    from tqdm import tqdm

    configs = [load_scenario(name) for name in scenarios]
    jobs = [(configs[k % len(configs)], seed_base, k, grid, noise) for k in range(count)]
    bar = partial(tqdm, total=count, desc="scenes", disable=not progress, leave=False)
    if workers <= 0:
        return list(bar(map(_scene_at, jobs)))
    with multiprocessing.get_context(WORKER_CONTEXT).Pool(workers) as pool:
        return list(bar(pool.imap(_scene_at, jobs, chunksize=8)))
