"""Compare alignment policies across noise levels with the sweep API (what `roco-env compare` runs).

    python examples/compare_policies.py [--out runs/example_compare] [--quick]

Runs identity / coalign / roco / oracle at several noise levels on a crowded
intersection, resumably (results.jsonl), and writes report.md, summary.csv and
plots. ROCO_EXAMPLE_QUICK=1 (or --quick) shrinks the grid (used by the tests).
"""

from __future__ import annotations

import argparse
import os

from roco_env.sweeps import build_grid, run_sweep, write_report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="runs/example_compare")
    parser.add_argument("--workers", type=int, default=None, help="default: all cores")
    parser.add_argument("--quick", action="store_true", help="tiny grid")
    args = parser.parse_args()
    quick = args.quick or os.environ.get("ROCO_EXAMPLE_QUICK") == "1"

    cells = build_grid(
        scenarios=["crowded_intersection"],
        noises=[0.0, 0.8] if quick else [0.0, 0.2, 0.4, 0.6, 0.8],
        policies=["identity", "coalign", "roco", "oracle"],
        seeds=[0] if quick else [0, 1, 2],
        steps=2 if quick else 30,
        overrides={"cavs": 2} if quick else {},
    )
    outcome = run_sweep(cells, os.path.join(args.out, "results.jsonl"), workers=args.workers)
    report = write_report(outcome.records, args.out, title="Example: policy comparison")
    print(report.markdown)
    print("files:", ", ".join(str(p) for p in report.files))


if __name__ == "__main__":
    main()
