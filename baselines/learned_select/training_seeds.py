"""Choose among candidate policies on training seeds (never the held-out 0, 1, 2).

    nice -n 10 python baselines/learned_select/training_seeds.py --out runs/select_cand \
        --policies learned_select:weights=runs/cand/learned_select.pt [--seeds 3] \
        [--base reject_untested] [--workers 2]

Runs ``--base`` and every ``--policies`` spec on the mixed benchmark's grid (3 scenarios x
noise 0.2 / 0.8 / 1.5 / 3.0, late fusion, ``--steps`` 10) at training env seeds (1,000,000 and
up), appends the cells to ``OUT/results.jsonl`` in the ``roco-env compare`` layout
(``table.py`` reads it; a cell already there with the same weights, by the sha256 of the
spec's ``weights=`` file, is not run again) and prints, per condition,
each policy's mean AP@0.7 minus the base's on the same seeds (columns ``p1``, ``p2``, ...
in the order given).
"""

from __future__ import annotations

import hashlib
import json
import sys
from collections import defaultdict
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from privileged_bound import grid_parser

from roco_env.policies.spec import parse_policy_spec
from roco_env.sweeps.cells import build_grid
from roco_env.sweeps.episode import run_episode
from roco_env.training.rl.curriculum import TRAIN_SEED_BASE


def differences(records: list[dict], base: str, policies: list[str],
                names: list[str] | None = None) -> str:
    """A Markdown table: per condition, each policy's mean AP@0.7 minus ``base``'s; columns
    ``names`` (None: ``p1``, ``p2``, ... and a legend line per policy under the table)."""
    score: dict = defaultdict(dict)
    for record in records:
        cell = record["cell"]
        score[(cell["scenario"], cell["noise"], cell["policy"])][cell["seed"]] = \
            record["metrics"]["ap70"]
    legend = names is None
    names = names or [f"p{index + 1}" for index in range(len(policies))]
    lines = [f"| scenario | noise | {base} | " + " | ".join(names) + " |",
             "|---|---|---|" + "---|" * len(policies)]
    gains: dict[str, list[float]] = defaultdict(list)
    for scenario, noise in sorted({key[:2] for key in score}):
        reference = score[(scenario, noise, base)]
        cells = []
        for policy in policies:
            own = score.get((scenario, noise, policy), {})
            common = sorted(set(own) & set(reference))
            if common:
                gains[policy].append(float(np.mean([own[s] - reference[s] for s in common])))
            cells.append(f"{gains[policy][-1]:+.4f}" if common else "-")
        lines.append(f"| {scenario} | {noise} | {np.mean(list(reference.values())):.4f} | "
                     + " | ".join(cells) + " |")
    lines.append("| **mean** | all | | " + " | ".join(
        f"{np.mean(gains[policy]):+.4f}" if gains[policy] else "-" for policy in policies)
        + " |")
    if legend:
        lines += [f"{name}: {policy}" for name, policy in zip(names, policies, strict=True)]
    return "\n".join(lines)


def weights_sha256(policy: str) -> str:
    """The sha256 of the weights file a policy spec names (``weights=PATH``; "" without
    one): a cell recorded with other weights at the same path does not count as run."""
    path = dict(parse_policy_spec(policy).params).get("weights")
    return hashlib.sha256(Path(str(path)).read_bytes()).hexdigest() if path else ""


def ap70_record(cell) -> dict:
    """One episode of ``cell``, as a record of the ``roco-env compare`` layout holding its
    AP@0.7."""
    metrics, _ = run_episode(cell)
    return {"cell": {"scenario": cell.scenario, "noise": cell.noise, "policy": cell.policy,
                     "seed": cell.seed, "overrides": {}}, "metrics": {"ap70": metrics["ap70"]}}


def main(argv: list[str] | None = None) -> None:
    parser = grid_parser(__doc__.splitlines()[0], seeds=3)
    parser.add_argument("--policies", nargs="*", default=[])
    parser.add_argument("--base", default="reject_untested")
    parser.add_argument("--workers", type=int, default=1, choices=(1, 2))
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    sink_path = out / "results.jsonl"
    # as the records name them (build_grid's labels: parameters sorted, values normalised)
    base, *policies = (parse_policy_spec(p).label for p in [args.base, *args.policies])
    sha = {policy: weights_sha256(policy) for policy in [base, *policies]}

    def current(record: dict) -> bool:  # recorded with the weights the spec names now
        cell = record["cell"]
        return cell.get("weights_sha256", "") == sha.get(cell["policy"], "")
    recorded = [json.loads(line) for line in sink_path.read_text().splitlines()] \
        if sink_path.exists() else []
    done = {(r["cell"]["scenario"], r["cell"]["noise"], r["cell"]["policy"], r["cell"]["seed"])
            for r in recorded if current(r)}
    seeds = [TRAIN_SEED_BASE + index for index in range(args.seeds)]
    cells = [cell for cell in build_grid(args.scenarios, args.noise,
                                         [base, *policies], seeds, args.steps)
             if (cell.scenario, cell.noise, cell.policy, cell.seed) not in done]
    with sink_path.open("a") as sink, ProcessPoolExecutor(args.workers) as pool:
        for record in pool.map(ap70_record, cells):
            record["cell"]["weights_sha256"] = sha[record["cell"]["policy"]]
            sink.write(json.dumps(record) + "\n")
            sink.flush()
            print(*record["cell"].values(), round(record["metrics"]["ap70"], 4),
                  file=sys.stderr)
    records = [json.loads(line) for line in sink_path.read_text().splitlines()]
    print(differences([r for r in records if current(r)], base, policies))


if __name__ == "__main__":
    main()
