"""Choose the guard's reject margin on training seeds (never the held-out 0, 1, 2).

    nice -n 10 python baselines/learned_select/guard_margin.py --weights runs/hard_guard.pt \
        --margins 0 1 2 1e9 --out runs/guard_margin [--noise 3.0 1.5]

Runs roco_antialias and ``learned_select:weights=W,reject_margin=M`` for every margin on
the mixed benchmark's grid (3 scenarios x noise 0.2 / 0.8 / 1.5 / 3.0, late fusion,
``--steps`` 10) at training env seeds (1,000,000 and up, ``--seeds`` of them), appends the cells
to ``OUT/results.jsonl`` in the ``roco-env compare`` layout (table.py reads it) and prints,
per condition, each margin's mean AP@0.7 minus roco_antialias's on the same seeds. A huge
margin (1e9) rejects every slot the guard hands to the network: the rule without it.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from privileged_bound import grid_parser
from training_seeds import ap70_record, differences

from roco_env.policies.spec import parse_policy_spec
from roco_env.sweeps.cells import build_grid
from roco_env.training.rl.curriculum import TRAIN_SEED_BASE

BASE = "roco_antialias"


def main(argv: list[str] | None = None) -> None:
    parser = grid_parser(__doc__.splitlines()[0], seeds=5)
    parser.add_argument("--weights", required=True, help="a weights file with a guard")
    parser.add_argument("--margins", nargs="+", type=float, required=True)
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    # as the records name them (build_grid's labels)
    policies = [BASE] + [parse_policy_spec(f"learned_select:weights={args.weights},"
                                           f"reject_margin={margin:g}").label
                         for margin in args.margins]
    seeds = [TRAIN_SEED_BASE + index for index in range(args.seeds)]
    with (out / "results.jsonl").open("a") as sink:
        for cell in build_grid(args.scenarios, args.noise, policies, seeds, args.steps):
            record = ap70_record(cell)
            sink.write(json.dumps(record) + "\n")
            sink.flush()
            print(*record["cell"].values(), round(record["metrics"]["ap70"], 4),
                  file=sys.stderr)
    records = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    print(differences(records, BASE, policies[1:],
                      [f"margin {margin:g}" for margin in args.margins]))


if __name__ == "__main__":
    main()
