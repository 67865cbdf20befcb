"""Single-agent (EgoEnv) throughput for RL: what scoring only the controlled agent and lean
infos save, and what an asynchronous vector env of 2 workers gains over one env.

Setting: ``urban_intersection`` (4 CAVs, default density), noise 0.8 m / 0.8 deg, late
fusion, zero corrections, whole seeded episodes. Baselines in the same process: the
ego env scoring every agent with full infos (what ``EgoEnv`` did before it scored only its
agent), and one env stepped alone against ``gymnasium.make_vec(..., "async")`` with 2.
"""

from __future__ import annotations

import multiprocessing
import pickle
import statistics
import time

import gymnasium
import numpy as np
from gymnasium.vector.utils import create_shared_memory, write_to_shared_memory

from roco_env.benchmarks._timing import median_seconds
from roco_env.wrappers import EgoEnv

SETTING = dict(scenario="urban_intersection", sigma_t=0.8, sigma_r=0.8)
TARGET_ASYNC_SPEEDUP = 1.6


def _episode_rate(env: EgoEnv, steps: int) -> float:
    """Steps per second over one seeded episode of ``steps`` zero actions."""
    action = np.zeros(env.action_space.shape, dtype=np.float32)

    def episode() -> None:
        env.reset(seed=0)
        for _ in range(steps):
            env.step(action)

    return steps / median_seconds(episode, repeats=3, warmup=1)


def _info_bytes(env: EgoEnv) -> int:
    """Pickled size of one step's info (what a worker process sends back)."""
    env.reset(seed=0)
    *_, info = env.step(np.zeros(env.action_space.shape, dtype=np.float32))
    return len(pickle.dumps(info))


def _worker_path(env: EgoEnv, steps: int) -> tuple[float, float, float]:
    """Median seconds of one env step, of pickling its result as an async worker sends it
    back, and of writing its observation into shared memory (what the worker adds)."""
    memory = create_shared_memory(env.observation_space, n=1, ctx=multiprocessing.get_context())
    action = np.zeros(env.action_space.shape, dtype=np.float32)
    env.reset(seed=0)
    times: list[tuple[float, float, float]] = []
    for _ in range(steps):
        start = time.perf_counter()
        observation, reward, terminated, truncated, info = env.step(action)
        stepped = time.perf_counter()
        pickle.dumps(((None, reward, terminated, truncated, info), True))
        pickled = time.perf_counter()
        write_to_shared_memory(env.observation_space, 0, observation, memory)
        times.append((stepped - start, pickled - stepped, time.perf_counter() - pickled))
    return tuple(statistics.median(column) for column in zip(*times, strict=True))


def _vector_rate(num_envs: int, mode: str, steps: int) -> float:
    """Env steps per second (all envs together) of a vector env of ``num_envs``."""
    envs = gymnasium.make_vec("roco/CollabPerceptionEgo-v0", num_envs=num_envs,
                              vectorization_mode=mode, max_cycles=10**6, info_level="metrics",
                              **SETTING)
    try:
        envs.reset(seed=list(range(num_envs)))
        action = np.zeros(envs.action_space.shape, dtype=np.float32)
        envs.step(action)  # workers warm (imports, compiled kernels)
        start = time.perf_counter()
        for _ in range(steps):
            envs.step(action)
        return num_envs * steps / (time.perf_counter() - start)
    finally:
        envs.close()


def run(quick: bool) -> list[str]:
    steps = 20 if quick else 100
    before = EgoEnv(max_cycles=steps, evaluate_others=True, **SETTING)
    scored = EgoEnv(max_cycles=steps, **SETTING)
    lean = EgoEnv(max_cycles=steps, info_level="metrics", **SETTING)
    rates = [_episode_rate(env, steps) for env in (before, scored, lean)]
    sizes = [_info_bytes(env) for env in (before, lean)]
    lines = [
        f"setting: {SETTING['scenario']}, {len(before.env.possible_agents)} agents, noise 0.8, "
        "late fusion, zero corrections",
        f"EgoEnv scoring every agent, full infos: {rates[0]:.0f} steps/s (baseline)",
        f"EgoEnv scoring its agent only:          {rates[1]:.0f} steps/s "
        f"({rates[1] / rates[0]:.2f}x)",
        f"  ... with info_level='metrics':        {rates[2]:.0f} steps/s "
        f"({rates[2] / rates[0]:.2f}x)",
        f"info per step: {sizes[0] / 1e3:.1f} kB full, {sizes[1] / 1e3:.2f} kB metrics",
    ]
    step, pickling, sharing = _worker_path(lean, steps)
    lines.append(f"async worker path per step (metrics): pickling the result {pickling * 1e6:.0f} "
                 f"us + observation into shared memory {sharing * 1e6:.0f} us = "
                 f"{(pickling + sharing) / step:.1%} of the env step ({step * 1e3:.1f} ms)")
    vector_steps, rounds = (10, 1) if quick else (100, 5)
    pairs = [(_vector_rate(1, "sync", vector_steps), _vector_rate(2, "async", vector_steps))
             for _ in range(rounds)]  # interleaved: a shared machine's load hits both alike
    one = statistics.median(p[0] for p in pairs)
    two = statistics.median(p[1] for p in pairs)
    ratios = sorted(p[1] / p[0] for p in pairs)
    ratio = statistics.median(ratios)
    lines.append(f"make_vec async, 2 workers, info_level='metrics': {two:.0f} env steps/s vs one "
                 f"env {one:.0f} (median of {rounds} interleaved rounds: {ratio:.2f}x, rounds "
                 f"{ratios[0]:.2f}x..{ratios[-1]:.2f}x; target {TARGET_ASYNC_SPEEDUP}x on 2 "
                 f"free cores: {'met' if ratio >= TARGET_ASYNC_SPEEDUP else 'NOT met'})")
    return lines
