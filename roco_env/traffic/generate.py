"""Stress-scenario generator: crowded, repetitive synthetic scenes as validated YAML.

``generate_scenario`` builds a ScenarioConfig for a synthetic layout with tight
gaps, previews one episode from ``seed`` to summarise it (vehicle count and
nearest-neighbour gaps), and can write the scenario YAML and an OPV2V export
of the preview episode. The CLI ``roco-env scenario generate`` is a thin
wrapper around :func:`generate` (see roco_env/cli/scenario_command.py).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from roco_env.geometry import box_corners_bev
from roco_env.scenario import (
    SOURCE_LAYOUTS,
    ScenarioConfig,
    load_scenario,
    save_scenario,
    scenario_file_name,
    scenario_from_dict,
    scenario_to_dict,
)
from roco_env.traffic.opv2v_export import export_opv2v, prepare_export_folder
from roco_env.traffic.state import WorldState
from roco_env.traffic.synthetic import make_synthetic

SYNTHETIC_LAYOUTS = SOURCE_LAYOUTS["synthetic"]
# Tight spawn gaps (m) per layout: crowding makes matching ambiguous.
STRESS_MIN_GAP = {"highway": 1.5, "intersection": 1.5, "roundabout": 1.5, "parking_lot": 0.5,
                  "traffic_jam": 1.0}


@dataclass(frozen=True)
class Summary:
    """Preview statistics of a generated scene (first frame)."""

    vehicles: int
    mean_gap: float
    median_gap: float
    mean_centre_distance: float

    def lines(self) -> list[str]:
        return [
            f"vehicles: {self.vehicles}",
            f"nearest-neighbour gap (footprint edge to edge): mean {self.mean_gap:.2f} m, "
            f"median {self.median_gap:.2f} m",
            f"nearest-neighbour centre distance: mean {self.mean_centre_distance:.2f} m",
        ]


def _point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    t = np.clip(np.sum((p - a) * ab, -1) / np.maximum(np.sum(ab * ab, -1), 1e-12), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[..., None] * ab), axis=-1)


def nearest_gaps(boxes: np.ndarray, neighbours: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Per box: the smallest edge-to-edge BEV footprint distance (m) to any other box, and
    the nearest centre distance (m). Footprints must not overlap. Candidates are the
    ``neighbours`` nearest centres (KD-tree); the rectangle distance is the minimum of
    vertex-to-edge distances both ways (exact for disjoint convex polygons)."""
    boxes = np.asarray(boxes, dtype=float).reshape(-1, 7)
    n = boxes.shape[0]
    if n < 2:
        return np.full(n, np.nan), np.full(n, np.nan)
    k = min(neighbours, n - 1)
    dist, idx = cKDTree(boxes[:, :2]).query(boxes[:, :2], k=k + 1)
    i = np.repeat(np.arange(n), k)
    j = idx[:, 1:].reshape(-1)
    corners = box_corners_bev(boxes)
    ci, cj = corners[i], corners[j]
    ends_i, ends_j = np.roll(ci, -1, axis=1), np.roll(cj, -1, axis=1)
    d_ij = _point_segment_distance(ci[:, :, None], cj[:, None], ends_j[:, None])
    d_ji = _point_segment_distance(cj[:, :, None], ci[:, None], ends_i[:, None])
    pair = np.minimum(d_ij.min(axis=(1, 2)), d_ji.min(axis=(1, 2)))
    return pair.reshape(n, k).min(axis=1), dist[:, 1]


def summarize(state: WorldState) -> Summary:
    gaps, centres = nearest_gaps(state.object_boxes)
    return Summary(state.num_objects, float(np.mean(gaps)), float(np.median(gaps)),
                   float(np.mean(centres)))


def stress_config(layout: str, density: float, cavs: int, rsus: int, seed: int,
                  min_gap: float | None = None, base: str = "urban_intersection") -> ScenarioConfig:
    """A validated config: ``base`` scenario's sensors/noise/detector with the given traffic."""
    if layout not in SYNTHETIC_LAYOUTS:
        raise ValueError(f"layout={layout!r} is not allowed; choose one of {list(SYNTHETIC_LAYOUTS)}")
    data = scenario_to_dict(load_scenario(base))
    data["name"] = f"stress_{layout}_d{density:g}_s{seed}"
    data["description"] = (f"Generated stress scenario: {layout}, density {density:g}, "
                           f"{cavs} CAVs + {rsus} RSUs (preview seed {seed}).")
    data["traffic"].update(source="synthetic", layout=layout, density=float(density),
                           min_gap=float(STRESS_MIN_GAP[layout] if min_gap is None else min_gap))
    data["agents"].update(cavs=cavs, rsus=rsus)
    return scenario_from_dict(data, where="generated scenario")


EXPORT_FRAMES = 10  # frames of the preview episode written to export_dir by default


def generate(layout: str, density: float, cavs: int, rsus: int, seed: int,
             output: str | Path | None = None, export_dir: str | Path | None = None,
             frames: int = EXPORT_FRAMES, min_gap: float | None = None,
             overwrite: bool = False) -> tuple[ScenarioConfig, Summary]:
    """Build, preview (seeded) and optionally write a stress scenario.

    output: YAML path to write (re-validated by loading it back). export_dir: write
    ``frames`` preview frames there as OPV2V label folders (a non-empty folder only
    with ``overwrite``, see :func:`roco_env.traffic.opv2v_export.export_opv2v`).
    """
    config = stress_config(layout, density, cavs, rsus, seed, min_gap)
    path = None if output is None else scenario_file_name(output, "scenario output")
    if export_dir is not None:  # refuse before writing anything
        if frames < 1:
            raise ValueError(f"frames must be >= 1; got {frames}")
        prepare_export_folder(export_dir, overwrite)
    source = make_synthetic(config)
    states = [source.reset(np.random.default_rng(seed))]
    summary = summarize(states[0])
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        load_scenario(save_scenario(config, path))
    if export_dir is not None:
        states += [source.step(config.traffic.dt) for _ in range(frames - 1)]
        export_opv2v(states, export_dir, overwrite=overwrite)
    return config, summary
