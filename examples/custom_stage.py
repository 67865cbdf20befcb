"""Plug in your own pipeline stages: a detector that loses boxes in rain and a late
fusion that trusts collaborators' scores less than the ego's own.

Every stage of the pipeline (traffic, noise, detector, fusion, reward) is found by name
in a registry (roco_env.stages). ``roco_env.register_stage(kind, name, factory,
params=...)`` adds a name; a scenario then selects it like a built-in one, and its
parameters are checked by the dataclass you declare (``spec`` fields: type, range,
documentation), with the same error messages as every other scenario key. An installed
package does the same with an entry point in the group ``roco_env.<kind>``.

    python examples/custom_stage.py [--steps 10] [--quick]
"""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass
from typing import Any

import numpy as np

import roco_env
from roco_env.fusion.late import LateFusion, kept_items, merge_many
from roco_env.policies import make_policy
from roco_env.schema import spec
from roco_env.sensing.detector import AgentDetections, Perception, realistic_detector


@dataclass
class RainParams:
    """The rain detector's parameters (``detector.params``)."""

    loss: float = spec(0.3, low=0.0, high=1.0, high_open=True,
                       doc="share of the realistic detector's boxes lost to rain")


class RainDetector:
    """The realistic detector, then each box lost with probability ``loss`` (drawn from the
    env's sensing stream, so episodes repeat with the seed)."""

    def __init__(self, params: dict[str, Any], region: Any = None) -> None:
        self.loss = RainParams(**params).loss  # params: the keys the scenario gave, checked
        self.clear_weather = realistic_detector({})
        self.axial_headings = self.clear_weather.axial_headings

    def perceive(self, state: Any, visibility: Any, rng: np.random.Generator) -> Perception:
        detections = self.clear_weather.perceive(state, visibility, rng).detections
        kept = [rng.random(len(d.scores)) >= self.loss for d in detections]
        return Perception([AgentDetections(d.boxes[k], d.uncertainty[k], d.scores[k],
                                           d.object_ids[k])
                           for d, k in zip(detections, kept, strict=True)])


@dataclass
class DiscountParams:
    """The discounted fusion's parameters (``fusion.params``)."""

    weight: float = spec(0.8, low=0.0, high=1.0, doc="factor on collaborators' scores")


class DiscountedLateFusion(LateFusion):
    """Late fusion with every collaborator's score multiplied by ``fusion.params.weight``:
    at equal confidence the NMS keeps the ego's own box."""

    def __init__(self, config: Any, detector: Any) -> None:
        self.weight = DiscountParams(**config.fusion.params).weight

    def fuse(self, frame: Any, egos: list[int], kept: list[np.ndarray],
             poses: list[np.ndarray]) -> list:
        return merge_many([
            (frame.views[k].boxes, frame.views[k].scores,
             kept_items(frame.views[k].collab_boxes, mask),
             [self.weight * s for s in kept_items(frame.views[k].collab_scores, mask)], pose)
            for k, mask, pose in zip(egos, kept, poses, strict=True)])


def mean_ap70(policy_name: str, steps: int, **overrides: Any) -> float:
    """Mean AP@0.7 over the evaluated agents and steps of one seeded episode."""
    env = roco_env.parallel_env("urban_intersection", max_cycles=steps, sigma_t=0.6,
                                sigma_r=0.6, **overrides)
    observations, infos = env.reset(seed=0)
    policy = make_policy(policy_name)
    values = []
    while env.agents:
        actions = {agent: policy(observations[agent], infos[agent]) for agent in env.agents}
        observations, _, _, _, infos = env.step(actions)
        values += [info["ap70"] for info in infos.values()
                   if info.get("evaluated") and info["ap70"] >= 0]
    return float(np.mean(values)) if values else float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=10, help="steps per episode")
    parser.add_argument("--quick", action="store_true", help="3 steps (the test's run)")
    args = parser.parse_args()
    steps = 3 if args.quick or os.environ.get("ROCO_EXAMPLE_QUICK") else args.steps

    roco_env.register_stage("detector", "rain", RainDetector, params=RainParams)
    roco_env.register_stage("fusion", "discounted", DiscountedLateFusion, params=DiscountParams)
    print("detectors:", ", ".join(roco_env.available_stages("detector")))
    print("fusion methods:", ", ".join(roco_env.available_stages("fusion")))
    try:  # the parameters are checked like any scenario key
        roco_env.parallel_env("urban_intersection", detector="rain",
                              **{"detector.params.loss": 1.5})
    except ValueError as error:
        print("checked:", error)

    settings = {
        "clear, late fusion": {},
        "rain 30%, late fusion": {"detector": "rain"},
        "rain 30%, discounted fusion": {"detector": "rain", "fusion": "discounted",
                                        "fusion.params.weight": 0.8},
    }
    print(f"\nmean AP@0.7 over {steps} steps, urban_intersection, noise 0.6 m / 0.6 deg")
    print(f"{'setting':32s} {'identity':>9s} {'roco':>9s}")
    for label, overrides in settings.items():
        row = [mean_ap70(policy, steps, **overrides) for policy in ("identity", "roco")]
        print(f"{label:32s} " + " ".join(f"{value:9.3f}" for value in row))


if __name__ == "__main__":
    main()
