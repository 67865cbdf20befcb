"""Learned detector: inference time per agent and environment throughput with it.

Setting: ``urban_intersection`` (4 CAVs + 1 RSU = 5 agents, every one an ego),
seed 0, the shipped weights on the CPU. Inference = one step's LiDAR scans,
rasters, batched encoder + heads and decoding of all agents, divided by the
agent count. Env throughput: identity policy, whole steps, for the parametric
``realistic`` detector with late fusion, and the learned detector with late
and with intermediate fusion, all in this process (ratios are meaningful, the
absolute numbers depend on the machine's load), with the detector's default one
thread and, last, learned + intermediate with one thread per core
(``detector.params.threads``). Each figure is given in wall time and in this process's
CPU time (``time.process_time``: what other jobs on a shared machine disturb least;
with one thread the two agree on an idle machine, with more the CPU time adds up the
threads' time).
"""

from __future__ import annotations

import time

import numpy as np

from roco_env.benchmarks._timing import median_seconds
from roco_env.env import CollabPerceptionEnv

SETTING = dict(scenario="urban_intersection", cavs=4, rsus=1)
TARGET_MS_PER_AGENT = 15.0
TARGET_STEPS_PER_S = 15.0
CLOCKS = {"wall": time.perf_counter, "CPU": time.process_time}


def _steps_per_second(steps: int, repeats: int, **overrides) -> dict[str, float]:
    env = CollabPerceptionEnv(**SETTING, max_cycles=10**9, **overrides)
    env.reset(seed=0)
    zeros = {a: np.zeros((env.config.max_collaborators, 3)) for a in env.possible_agents}

    def run_steps() -> None:
        for _ in range(steps):
            env.step(zeros)

    return {name: steps / median_seconds(run_steps, repeats=repeats, clock=clock)
            for name, clock in CLOCKS.items()}


def run(quick: bool) -> list[str]:
    import torch

    from roco_env.sensing import compute_visibility
    from roco_env.sensing.learned import LearnedDetector
    from roco_env.sweeps.backends import default_workers

    repeats = 3 if quick else 7
    process_threads = torch.get_num_threads()
    cores = default_workers()  # all cores this process may use
    env = CollabPerceptionEnv(**SETTING, max_cycles=10**9, detector="learned")
    env.reset(seed=0)
    state = env.unwrapped._frame.state
    visibility = compute_visibility(state)
    detector = LearnedDetector()
    rng = np.random.default_rng(0)
    n = state.num_agents
    rasters = detector.rasters(state, visibility, rng)
    lines = []
    for name, clock in CLOCKS.items():
        total = median_seconds(lambda: detector.perceive(state, visibility, rng),
                               repeats=repeats, clock=clock)
        network = median_seconds(
            lambda: detector.decode(detector.encode(rasters), np.zeros(n)), repeats=repeats,
            clock=clock)
        lines.append(
            f"inference per agent, {name} time (scan + raster + network + decode, {n} agents "
            f"in one batch): {1e3 * total / n:.1f} ms (target <= {TARGET_MS_PER_AGENT:.0f} ms); "
            f"network + decode alone {1e3 * network / n:.1f} ms")
    steps = 2 if quick else 5
    rates = {
        "realistic + late": _steps_per_second(steps, repeats, detector="realistic"),
        "learned + late": _steps_per_second(steps, repeats, detector="learned"),
        "learned + intermediate": _steps_per_second(steps, repeats, detector="learned",
                                                    fusion="intermediate"),
    }
    if cores > 1:
        rates[f"learned + intermediate, {cores} threads"] = _steps_per_second(
            steps, repeats, detector="learned", fusion="intermediate",
            **{"detector.params": {"threads": cores}})
    torch.set_num_threads(process_threads)  # every detector set it process-wide
    for name, rate in rates.items():
        target = f"; target >= {TARGET_STEPS_PER_S:.0f}" if name.startswith("learned + int") else ""
        lines.append(f"env steps/s, {name}: " + ", ".join(
            f"{rate[c]:.1f} {c} ({rate[c] / rates['realistic + late'][c]:.2f}x the parametric "
            f"detector)" for c in CLOCKS) + target)
    return lines
