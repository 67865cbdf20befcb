"""Quality of the learned detector in the environment, on held-out seeds.

    python -m roco_env.training.assessment --seeds 4 --steps 10 --out DIR [--weights FILE]

Measured on ``urban_intersection`` episodes (env seeds 0..seeds-1; training and
validation scenes use other generators), every agent an ego, identity policy:

* **single agent** (``max_collaborators=0``, no pose noise): AP@0.3/0.5/0.7 of the
  learned detector and of the parametric ``realistic`` preset on the same frames
  (the traffic does not depend on the detector);
* **fusion with true poses**: late vs intermediate fusion of the learned detector, also
  split by where the objects' centres lie: inside the trained detector grid (a 70 m CAV's
  own raster), or beyond it, where only collaborators' maps can place them (there the intermediate boxes come
  from warped maps alone); the split matches each ego's fused boxes against its ground-truth boxes in the
  step info, within each region;
* **warp consistency**: a map decoded after a warp onto the fusion canvas against the
  same map's own boxes moved by that warp (validation scenes of urban_intersection,
  boxes scored above 0.3, pairs within 2 m): the centre error a warp alone adds, for a
  whole-cell shift, a sub-cell shift, rotations, and a half turn;
* **uncertainty calibration**: for every own detection labelled with a true object,
  the share of centre (x, y, agent frame) and yaw (modulo pi) errors within 1 and 2
  of the predicted sigmas (ideal for a Gaussian: 68% and 95%).

Weights: the shipped file, or ``--weights FILE`` (e.g. a ``train-detector`` output).
Writes ``assessment.json`` and ``assessment.md`` to DIR.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

import numpy as np

from roco_env.env import CollabPerceptionEnv
from roco_env.evaluation import info_frame_stats
from roco_env.geometry import se2_inverse, transform_boxes
from roco_env.metrics import APAccumulator
from roco_env.sensing.features import BevGrid
from roco_env.sensing.learned.model import (
    LearnedDetector,
    load_checkpoint,
    sha256_of,
    shipped_weights_path,
)
from roco_env.training.data import VALIDATION_SEED_BASE, make_scenes

# Warps (x m, y m, yaw rad) of the warp-consistency check; 16.0 and 3.2 m are whole
# cells of the 1.6 m feature grid, 16.7 and 3.5 m are not.
WARPS = {"whole cells": (16.0, 3.2, 0.0), "sub-cell shift": (16.7, 3.5, 0.0),
         "sub-cell, 0.3 rad": (16.7, 3.5, 0.3), "sub-cell, quarter turn": (16.7, 3.5, np.pi / 2),
         "half turn": (50.0, 0.0, np.pi)}

SCENARIO = "urban_intersection"


def _episode_ap(seeds: int, steps: int, calibration: list | None = None,
                grid: BevGrid | None = None, **overrides) -> dict[str, float]:
    """Pooled AP over all egos (and over the CAV egos alone), steps and seeds of episodes
    with zero corrections; with ``grid`` (the detector's, ego frame) also the AP inside it
    and beyond it."""
    acc, cav_acc = APAccumulator(), APAccumulator()
    regions = {"inside_grid": APAccumulator(), "beyond_grid": APAccumulator()}
    for seed in range(seeds):
        env = CollabPerceptionEnv(SCENARIO, max_cycles=steps, sigma_t=0.0, sigma_r=0.0,
                                  **overrides)
        env.reset(seed=seed)
        zeros = {a: np.zeros((env.config.max_collaborators, 3)) for a in env.possible_agents}
        while env.agents:
            if calibration is not None:
                calibration.append(_normalised_errors(env))
            _, _, _, _, infos = env.step(zeros)
            for agent, info in infos.items():
                stats = info_frame_stats(info)
                acc.add_stats(stats)
                if agent.startswith("cav"):
                    cav_acc.add_stats(stats)
                if grid is not None:
                    _add_by_region(regions, info, grid)
    out = {**{f"ap{round(t * 100)}": v for t, v in acc.ap().items()},
           **{f"cav_ap{round(t * 100)}": v for t, v in cav_acc.ap().items()}}
    if grid is not None:
        out.update({f"{name}_ap{round(t * 100)}": v for name, region in regions.items()
                    for t, v in region.ap().items()})
    return out


def _add_by_region(regions: dict[str, APAccumulator], info: dict, grid: BevGrid) -> None:
    """Match an ego's fused boxes to its ground truth (both from the step info, ego frame)
    inside ``grid`` and beyond it, each region on its own."""
    boxes = np.asarray(info["fused_boxes"])[np.asarray(info["fused_mask"], dtype=bool)]
    scores = np.asarray(info["fused_scores"])[np.asarray(info["fused_mask"], dtype=bool)]
    gt = np.asarray(info["gt_boxes"])[np.asarray(info["gt_mask"], dtype=bool)]
    pred_in = grid.cell_index(boxes[:, 0], boxes[:, 1])[0] >= 0
    gt_in = grid.cell_index(gt[:, 0], gt[:, 1])[0] >= 0
    regions["inside_grid"].add_frame(boxes[pred_in], scores[pred_in], gt[gt_in])
    regions["beyond_grid"].add_frame(boxes[~pred_in], scores[~pred_in], gt[~gt_in])


def _normalised_errors(env: CollabPerceptionEnv) -> np.ndarray:
    """|error| / sigma (K, 3) of every labelled own detection of the current frame."""
    frame = env.unwrapped._frame
    state = frame.state
    rows = []
    for a, det in enumerate(frame.detections):
        ok = det.object_ids >= 0
        if not ok.any():
            continue
        index = {int(o): k for k, o in enumerate(state.object_ids)}
        truth = transform_boxes(state.object_boxes[[index[int(o)] for o in det.object_ids[ok]]],
                                se2_inverse(state.agent_poses[a]))
        err = np.column_stack([det.boxes[ok, 0] - truth[:, 0], det.boxes[ok, 1] - truth[:, 1],
                               np.remainder(det.boxes[ok, 6] - truth[:, 6] + np.pi / 2, np.pi)
                               - np.pi / 2])
        rows.append(np.abs(err) / det.uncertainty[ok])
    return np.concatenate([np.zeros((0, 3)), *rows])


def assess(seeds: int, steps: int, weights: Path | None = None) -> dict:
    """The measurements of the module docstring (weights: None for the shipped file)."""
    calibration: list[np.ndarray] = []
    learned = {"detector": "learned",
               **({} if weights is None else {"detector.params": {"weights": str(weights)}})}
    grid = load_checkpoint(weights or shipped_weights_path()).grid
    out = {
        "single_learned": _episode_ap(seeds, steps, calibration, **learned,
                                      max_collaborators=0),
        "single_realistic": _episode_ap(seeds, steps, detector="realistic", max_collaborators=0),
        "late_learned_true_poses": _episode_ap(seeds, steps, grid=grid, **learned),
        "intermediate_learned_true_poses": _episode_ap(seeds, steps, grid=grid, **learned,
                                                       fusion="intermediate"),
        "late_realistic_true_poses": _episode_ap(seeds, steps, detector="realistic"),
    }
    z = np.concatenate(calibration)
    out["warp_consistency"] = warp_consistency(LearnedDetector(weights))
    out["calibration"] = {"n": int(z.shape[0]), **{
        f"within_{k}sigma_{name}": float(np.mean(z[:, i] <= k))
        for i, name in enumerate(("x", "y", "yaw")) for k in (1, 2)}}
    return out


def warp_consistency(detector: LearnedDetector, n_scenes: int = 3) -> dict[str, dict]:
    """Per warp of :data:`WARPS`: median and 90th percentile |x| and |y| centre error (m) of
    an agent's map decoded after the warp against its own boxes moved by it."""
    import torch

    from roco_env.fusion.intermediate import fuse_on_canvas, fusion_canvas

    scenes = make_scenes((SCENARIO,), n_scenes, VALIDATION_SEED_BASE + 7, detector.grid,
                         detector.noise)
    canvas, _ = fusion_canvas(detector.feature_grid, (-140.8, 140.8), (-40.0, 40.0))
    out = {}
    for name, warp in WARPS.items():
        errors = []
        for scene in scenes:
            own = detector.encode(torch.from_numpy(scene.rasters[:1]))
            mine = detector.decode(own, np.zeros(1))[0]
            # The map as a lone collaborator's, warped onto an empty ego's canvas.
            moved = fuse_on_canvas(torch.cat([torch.zeros_like(own), own]), [0], [[1]],
                                   [np.array([warp])], detector.feature_grid, canvas)
            got = detector.decode(moved, np.zeros(1), canvas)[0]
            expected = transform_boxes(mine.boxes[mine.scores > 0.3], np.array(warp))
            decoded = got.boxes[got.scores > 0.3]
            if not (len(expected) and len(decoded)):
                continue
            dist = np.hypot(expected[:, None, 0] - decoded[None, :, 0],
                            expected[:, None, 1] - decoded[None, :, 1])
            nearest = dist.argmin(axis=1)
            ok = dist[np.arange(len(expected)), nearest] < 2.0
            errors.append(np.abs(decoded[nearest[ok], :2] - expected[ok, :2]))
        e = np.concatenate([np.zeros((0, 2)), *errors])
        out[name] = {"warp": list(warp), "n": int(e.shape[0]),
                     **{f"{stat}_{axis}": float(f(e[:, k])) if e.shape[0] else float("nan")
                        for stat, f in (("median", np.median),
                                        ("p90", lambda v: np.percentile(v, 90)))
                        for k, axis in enumerate("xy")}}
    return out


def _markdown(result: dict, command: str) -> str:
    lines = [f"# Learned detector on {SCENARIO} (held-out seeds)", "", f"Command: `{command}`", "",
             f"Weights: sha256 `{result['weights_sha256']}`.", "",
             "All egos (4 CAVs with 70 m LiDARs + the RSU, whose raster covers its 100 m) "
             "and the CAV egos alone:", "",
             "| setting | AP@0.3 | AP@0.5 | AP@0.7 | CAVs AP@0.3 | CAVs AP@0.5 | CAVs AP@0.7 |",
             "|---|---|---|---|---|---|---|"]
    for key, value in result.items():
        if key.startswith(("single", "late", "intermediate")):
            lines.append("| " + " | ".join([key] + [f"{value[k]:.3f}" for k in (
                "ap30", "ap50", "ap70", "cav_ap30", "cav_ap50", "cav_ap70")]) + " |")
    lines += ["", "Fusion with true poses by where the objects lie: inside the trained "
              "detector grid (a CAV's own raster), or beyond it (where only collaborators' maps "
              "can place them):",
              "",
              "| setting | inside AP@0.5 | inside AP@0.7 | beyond AP@0.5 | beyond AP@0.7 |",
              "|---|---|---|---|---|"]
    for key in ("late_learned_true_poses", "intermediate_learned_true_poses"):
        lines.append("| " + " | ".join([key] + [f"{result[key][k]:.3f}" for k in (
            "inside_grid_ap50", "inside_grid_ap70", "beyond_grid_ap50", "beyond_grid_ap70")])
            + " |")
    lines += ["", "Warp consistency: a map decoded after a warp onto the fusion canvas against "
              "its own boxes moved by the warp (centre error, m):", "",
              "| warp (x m, y m, yaw rad) | boxes | median x / y | p90 x / y |",
              "|---|---|---|---|"]
    for name, w in result["warp_consistency"].items():
        lines.append(f"| {name} ({w['warp'][0]:g}, {w['warp'][1]:g}, {w['warp'][2]:.2f}) | "
                     f"{w['n']} | {w['median_x']:.2f} / {w['median_y']:.2f} | "
                     f"{w['p90_x']:.2f} / {w['p90_y']:.2f} |")
    cal = result["calibration"]
    lines += ["", f"Uncertainty calibration over {cal['n']} labelled own detections "
              "(share of |error| within k predicted sigmas; Gaussian ideal 0.68 / 0.95):", "",
              "| axis | within 1 sigma | within 2 sigma |", "|---|---|---|"]
    for name in ("x", "y", "yaw"):
        lines.append(f"| {name} | {cal[f'within_1sigma_{name}']:.3f} | "
                     f"{cal[f'within_2sigma_{name}']:.3f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m roco_env.training.assessment",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=4, help="env seeds 0..N-1 (default 4)")
    parser.add_argument("--steps", type=int, default=10, help="steps per episode (default 10)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--weights", type=Path, metavar="FILE",
                        help="weights file (default: the shipped one)")
    args = parser.parse_args(argv)
    if args.seeds < 1 or args.steps < 1:
        parser.error(f"--seeds and --steps must be >= 1; got {args.seeds} and {args.steps}")
    try:
        result = assess(args.seeds, args.steps, args.weights)
    except ValueError as exc:  # a missing, corrupt or mismatched weights file
        parser.error(str(exc))
    command = "python -m roco_env.training.assessment " + shlex.join(
        argv if argv is not None else sys.argv[1:])
    args.out.mkdir(parents=True, exist_ok=True)
    result = {"weights_sha256": sha256_of(args.weights or shipped_weights_path()), **result}
    (args.out / "assessment.json").write_text(json.dumps({"command": command, **result},
                                                         indent=2) + "\n")
    (args.out / "assessment.md").write_text(_markdown(result, command))
    print(_markdown(result, command))
    return 0


if __name__ == "__main__":
    sys.exit(main())
