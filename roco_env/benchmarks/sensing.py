"""Sensing speed: visibility + detection per step, BEV features, feature warping.

Scene: ``urban_intersection`` with the density raised to about 200 vehicles
(4 CAVs + 1 RSU = 5 agents). Baseline for visibility: the obvious dense
ray casting (every ray of every agent against every in-range footprint edge,
2D first hit), measured in the same process.
Targets: visibility + detection < 5 ms; features for one agent at
0.4 m over 140 m x 80 m < 10 ms.
"""

from __future__ import annotations

import numpy as np
import torch

from roco_env.benchmarks._timing import median_seconds
from roco_env.geometry import box_corners_bev, se2_inverse, transform_boxes
from roco_env.scenario import load_scenario
from roco_env.sensing import BevGrid, bev_features, compute_visibility, make_detector, warp_bev
from roco_env.traffic import make_traffic_source
from roco_env.traffic.state import WorldState

DENSITY_FOR_200 = 9.0  # vehicles per 100 m of lane giving ~200 vehicles on this layout


def dense_first_hit_fraction(state: WorldState, azimuth_resolution_deg: float = 0.2
                             ) -> np.ndarray:
    """Baseline (A, M): 2D visible fraction from a dense rays x footprint-edges matrix."""
    n_rays = int(round(360.0 / azimuth_resolution_deg))
    angles = 2.0 * np.pi * np.arange(n_rays) / n_rays
    u = np.stack([np.cos(angles), np.sin(angles)], axis=1)  # (R, 2)
    fraction = np.zeros((state.num_agents, state.num_objects))
    for a in range(state.num_agents):
        near = np.flatnonzero(
            (np.hypot(*(state.object_boxes[:, :2] - state.agent_poses[a, :2]).T)
             <= state.sensor_ranges[a]) & (state.object_ids != state.agent_object_ids[a]))
        local = transform_boxes(state.object_boxes[near], se2_inverse(state.agent_poses[a]))
        p0 = box_corners_bev(local)[None]  # (1, K, 4, 2)
        edge = np.roll(p0, -1, axis=2) - p0
        ux, uy = u[:, 0, None, None], u[:, 1, None, None]  # (R, 1, 1)
        denom = ux * edge[..., 1] - uy * edge[..., 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (p0[..., 0] * edge[..., 1] - p0[..., 1] * edge[..., 0]) / denom
            s = (p0[..., 0] * uy - p0[..., 1] * ux) / denom
        t = np.where((s >= 0) & (s <= 1) & (t > 0), t, np.inf).min(axis=2)  # (R, K)
        crossing = np.isfinite(t)
        first = crossing & (t == t.min(axis=1, keepdims=True))
        fraction[a, near] = first.sum(0) / np.maximum(crossing.sum(0), 1)
    return fraction


def run(quick: bool) -> list[str]:
    """Medians of the sensing stages (see module docstring)."""
    repeats = 5 if quick else 25
    config = load_scenario("urban_intersection", density=DENSITY_FOR_200)
    state = make_traffic_source(config).reset(np.random.default_rng(0))
    detector = make_detector(config.detector)
    rng = np.random.default_rng(0)

    def sense() -> None:
        detector.detect(state, compute_visibility(state), rng)

    t_sense = median_seconds(sense, repeats, warmup=2)
    t_vis = median_seconds(lambda: compute_visibility(state), repeats, warmup=1)
    t_dense = median_seconds(lambda: dense_first_hit_fraction(state), max(repeats // 5, 2), 1)
    visibility = compute_visibility(state)
    grid = BevGrid((-70.0, 70.0), (-40.0, 40.0), 0.4)
    t_feat = median_seconds(lambda: bev_features(visibility, 0, grid), repeats, warmup=1)
    feats = torch.stack([bev_features(visibility, a, grid) for a in range(5)])
    poses = np.tile([[2.0, -1.0, 0.05]], (5, 1))
    t_warp = median_seconds(lambda: warp_bev(feats, poses, grid), repeats, warmup=1)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        t_warp_1 = median_seconds(lambda: warp_bev(feats, poses, grid), repeats, warmup=1)
    finally:
        torch.set_num_threads(threads)
    return [
        f"scene: {state.num_objects} vehicles, {state.num_agents} agents "
        f"({', '.join(state.agent_ids)})",
        f"visibility + detection, all agents: {t_sense * 1e3:.2f} ms/step "
        f"(target < 5 ms: {'met' if t_sense < 5e-3 else 'MISSED'})",
        f"  visibility alone: {t_vis * 1e3:.2f} ms; dense rays x edges baseline: "
        f"{t_dense * 1e3:.1f} ms ({t_dense / t_vis:.1f}x slower)",
        f"BEV features, 1 agent, {grid.H}x{grid.W} cells at 0.4 m: {t_feat * 1e3:.2f} ms "
        f"(target < 10 ms: {'met' if t_feat < 1e-2 else 'MISSED'})",
        f"warp_bev, 5 maps of 3x{grid.H}x{grid.W}: {t_warp * 1e3:.2f} ms with {threads} torch "
        f"threads, {t_warp_1 * 1e3:.2f} ms with 1 ({t_warp / t_warp_1:.1f}x)",
    ]
