"""Choose the guard's reject margin on training seeds (never the held-out 0, 1, 2).

    nice -n 10 python baselines/learned_select/guard_margin.py --weights runs/hard_guard.pt \
        --margins 0 1 2 1e9 --out runs/guard_margin [--noise 3.0 1.5]

Runs roco_antialias and ``learned_select:weights=W,reject_margin=M`` for every margin on
the mixed benchmark's grid (3 scenarios x noise 0.2 / 0.8 / 1.5 / 3.0, late fusion, 10
steps) at training env seeds (1,000,000 and up, ``--seeds`` of them), appends the cells
to ``OUT/results.jsonl`` in the ``roco-env compare`` layout (table.py reads it) and prints,
per condition, each margin's mean AP@0.7 minus roco_antialias's on the same seeds. A huge
margin (1e9) rejects every slot the guard hands to the network: the rule without it.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from training_seeds import differences

from roco_env.sweeps.cells import build_grid
from roco_env.sweeps.episode import run_episode
from roco_env.training.rl.curriculum import TRAIN_SEED_BASE

BASE = "roco_antialias"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--weights", required=True, help="a weights file with a guard")
    parser.add_argument("--margins", nargs="+", type=float, required=True)
    parser.add_argument("--out", required=True)
    parser.add_argument("--scenarios", nargs="+",
                        default=["urban_intersection", "parking_lot", "v2xset_like"])
    parser.add_argument("--noise", nargs="+", type=float, default=[0.2, 0.8, 1.5, 3.0])
    parser.add_argument("--seeds", type=int, default=5)
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    policies = [BASE] + [f"learned_select:weights={args.weights},reject_margin={margin:g}"
                         for margin in args.margins]
    seeds = [TRAIN_SEED_BASE + index for index in range(args.seeds)]
    with (out / "results.jsonl").open("a") as sink:
        for cell in build_grid(args.scenarios, args.noise, policies, seeds, 10):
            metrics, _ = run_episode(cell)
            sink.write(json.dumps({"cell": {"scenario": cell.scenario, "noise": cell.noise,
                                            "policy": cell.policy, "seed": cell.seed,
                                            "overrides": {}},
                                   "metrics": {"ap70": metrics["ap70"]}}) + "\n")
            sink.flush()
            print(cell.scenario, cell.noise, cell.policy, cell.seed,
                  round(metrics["ap70"], 4), file=sys.stderr)
    records = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    print(differences(records, BASE, policies[1:],
                      [f"margin {margin:g}" for margin in args.margins]))


if __name__ == "__main__":
    main()
