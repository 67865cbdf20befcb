"""Sweep throughput: the local backend on all cores vs 1 process, and Ray vs local.

One small grid (crowded_intersection, coalign + roco, noise 0.4, several seeds)
runs into a fresh results file per repetition. Reported: median wall time of
the whole sweep for (a) 1 process (``workers=1``, cells in this process),
(b) the local process pool on all cores, (c) Ray on all cores started by the
sweep (``ray.init`` + shutdown counted), (d) Ray already running (a cluster's
case); speed ratios vs (a) and (b). A process keeps its local pool between sweeps,
so (b) is a process's later sweep; its first, which starts the fork server and the
workers, is timed once and reported beside it. Target: (b) >= 1.8x faster than (a)
on 2 cores.
"""

from __future__ import annotations

import statistics
import tempfile
from pathlib import Path

from roco_env.benchmarks._timing import median_seconds
from roco_env.sweeps.backends import default_workers
from roco_env.sweeps.cells import build_grid
from roco_env.sweeps.sweep import run_sweep


def _grid(quick: bool):
    return build_grid(["crowded_intersection"], [0.4], ["coalign", "roco"],
                      list(range(2 if quick else 4)), steps=10 if quick else 12)


def _timer(cells, backend: str, workers: int):
    def sweep() -> None:
        with tempfile.TemporaryDirectory() as folder:
            outcome = run_sweep(cells, Path(folder) / "results.jsonl", backend=backend,
                                workers=workers, progress=False)
        if outcome.failed:
            raise RuntimeError(f"{outcome.failed} benchmark cells failed")
    return sweep


def _interleaved(timers: list, repeats: int) -> list[float]:
    """Median time of each timer, alternating them so a load change on the shared
    machine hits all of them alike."""
    samples: list[list[float]] = [[] for _ in timers]
    for _ in range(repeats):
        for timer, times in zip(timers, samples, strict=True):
            times.append(median_seconds(timer, repeats=1, warmup=0))
    return [statistics.median(times) for times in samples]


def run(quick: bool) -> list[str]:
    cells = _grid(quick)
    cores = default_workers()
    repeats = 1 if quick else 5
    _timer(cells, "local", 1)()  # warm-up: this process's imports and caches
    first_pool = median_seconds(_timer(cells, "local", cores), repeats=1, warmup=0)
    serial, local = _interleaved([_timer(cells, "local", 1), _timer(cells, "local", cores)],
                                 repeats)
    lines = [
        f"grid: {len(cells)} cells x {cells[0].steps} steps ({cells[0].scenario}, "
        f"{', '.join(sorted({c.policy for c in cells}))}); {cores} cores",
        f"1 process:            {serial:7.2f} s",
        f"local pool x{cores}:        {local:7.2f} s   speedup vs 1 process {serial / local:4.2f}x "
        "(target >= 1.8x on 2 cores)",
        f"local pool x{cores}, first: {first_pool:7.2f} s   (starts the fork server and the "
        "workers; later sweeps reuse them)",
    ]
    try:
        import ray
    except ImportError:
        return lines + ["ray: not installed (pip install roco-env[ray]); skipped"]
    # dominated by starting Ray and importing roco_env in its workers: one run is enough
    ray_cold = median_seconds(_timer(cells, "ray", cores), repeats=1, warmup=0)
    ray.init(num_cpus=cores, include_dashboard=False, log_to_driver=False)
    try:
        ray_warm = median_seconds(_timer(cells, "ray", cores), repeats=repeats, warmup=1)
    finally:
        ray.shutdown()
    lines += [
        f"ray x{cores} (incl. init): {ray_cold:7.2f} s   vs local pool {local / ray_cold:4.2f}x, "
        f"vs 1 process {serial / ray_cold:4.2f}x",
        f"ray x{cores} (running):    {ray_warm:7.2f} s   vs local pool {local / ray_warm:4.2f}x, "
        f"vs 1 process {serial / ray_warm:4.2f}x",
    ]
    return lines
