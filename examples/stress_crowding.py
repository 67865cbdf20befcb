"""Stress test: generate a crowded, repetitive scenario and see where alignment breaks.

Generates a parking lot (rows of identical cars, the hard case for matching) with
``roco_env.traffic.generate``, prints its summary, then compares identity / coalign /
roco on it at two noise levels.

    python examples/stress_crowding.py [--layout parking_lot] [--density 0.9] [--quick]

Same as: roco-env scenario generate --layout parking_lot --density 0.9 -o my.yaml
         roco-env compare --scenario my.yaml --policies identity coalign roco --noise 0.4 0.8
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from roco_env.sweeps import build_grid, run_sweep, write_report
from roco_env.traffic.generate import generate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--layout", default="parking_lot",
                        help="highway | intersection | roundabout | parking_lot | traffic_jam")
    parser.add_argument("--density", type=float, default=0.9,
                        help="vehicles per 100 m of lane (parking_lot: fill ratio 0..1)")
    parser.add_argument("--out", default="runs/stress_crowding")
    parser.add_argument("--quick", action="store_true", help="2 CAVs, 2 steps, 1 seed")
    args = parser.parse_args()
    quick = args.quick or os.environ.get("ROCO_EXAMPLE_QUICK") == "1"
    out = Path(args.out)

    scenario_file = out / f"{args.layout}_{args.density:g}.yaml"
    config, summary = generate(args.layout, args.density, cavs=2 if quick else 4, rsus=1, seed=0,
                               output=scenario_file)
    print(f"generated {scenario_file} ({config.name})")
    print("\n".join(f"  {line}" for line in summary.lines()))

    cells = build_grid([str(scenario_file)], noises=[0.4, 0.8],
                       policies=["identity", "coalign", "roco"], seeds=[0] if quick else [0, 1],
                       steps=2 if quick else 20)
    outcome = run_sweep(cells, out / "results.jsonl")
    report = write_report(outcome.records, out, title=f"Stress: {config.name}")
    print(report.markdown)


if __name__ == "__main__":
    main()
