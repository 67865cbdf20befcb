"""Traffic step cost: synthetic IDM traffic at 50/200/400 vehicles, and highway-env.

Prints the median step time per size, the growth ratio against the 50-vehicle
baseline measured in the same process (linear scaling would be 4x and 8x),
and the median highway-env step (10 Hz, IDLE action).
"""

from __future__ import annotations

import numpy as np

from roco_env.benchmarks._timing import median_seconds
from roco_env.scenario import scenario_from_dict
from roco_env.traffic import make_traffic_source

SIZES = (50, 200, 400)


def _synthetic(vehicles: int):
    # highway, 3 lanes per direction, 1000 m: density = vehicles per 100 m of lane
    config = scenario_from_dict({"traffic": {"layout": "highway", "lanes": 3, "length": 1000.0,
                                             "density": vehicles / 60.0, "min_gap": 2.0},
                                 "agents": {"cavs": 4, "rsus": 1}})
    source = make_traffic_source(config)
    state = source.reset(np.random.default_rng(0))
    return source, state.num_objects


def run(quick: bool = False) -> list[str]:
    repeats = 50 if quick else 400
    lines, base = [], None
    for size in SIZES:
        source, count = _synthetic(size)
        seconds = median_seconds(lambda s=source: s.step(0.1), repeats=repeats, warmup=20)
        base = base or seconds
        lines.append(f"synthetic step, {count} vehicles: median {seconds * 1e3:.3f} ms "
                     f"({seconds / base:.2f}x the {SIZES[0]}-vehicle step)")
    config = scenario_from_dict({"traffic": {"source": "highway_env", "layout": "highway",
                                             "density": 2.0, "lanes": 3},
                                 "agents": {"cavs": 2, "rsus": 0}})
    source = make_traffic_source(config)
    state = source.reset(np.random.default_rng(0))
    seconds = median_seconds(lambda: source.step(0.1), repeats=10 if quick else 40, warmup=2)
    lines.append(f"highway-env step (highway-v0, {state.num_objects} vehicles, 10 Hz): "
                 f"median {seconds * 1e3:.2f} ms")
    return lines
