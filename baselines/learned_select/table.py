"""Mean AP@0.7 per condition and overall of every policy in ``roco-env compare`` folders.

    python baselines/learned_select/table.py [--digits 4] runs/bench_fixed runs/bench_nofusion \
        runs/bench_learned

Reads each folder's ``results.jsonl`` (one line per finished cell: one episode of one
policy at one scenario, noise level and seed) and prints a Markdown table: rows are
(scenario, noise), columns the policies (a ``fusion=none`` cell is the column
``no_fusion``), each entry the mean over seeds of the episode's dataset AP@0.7; the last
rows are the mean over all conditions and each policy's count of conditions where it is
the best (ties count for each), to ``--digits`` decimals (default 3). Bold marks the
best per row among the policies that see no privileged truth: ``oracle`` (the true
poses), the ``bound_*`` columns of ``privileged_bound.py``, the ``headroom_*`` ones of
``headroom.py`` / ``headroom_c.py`` and the ``truth_*`` ones of ``choice_probe.py`` read
the truth: upper bounds or heuristics, not contenders.
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

PRIVILEGED = ("oracle", "bound_", "headroom", "truth_")  # column names that start so read the truth


def load(folders: list[str]) -> dict[tuple[str, float], dict[str, list[float]]]:
    """(scenario, noise) -> policy column -> per-seed AP@0.7."""
    table: dict = defaultdict(lambda: defaultdict(list))
    for folder in folders:
        for line in (Path(folder) / "results.jsonl").read_text().splitlines():
            record = json.loads(line)
            if record.get("status", "ok") != "ok" or "metrics" not in record:
                continue
            cell = record["cell"]
            column = "no_fusion" if cell["overrides"].get("fusion") == "none" else cell["policy"]
            table[(cell["scenario"], cell["noise"])][column].append(record["metrics"]["ap70"])
    return table


def markdown(table: dict, digits: int = 3) -> str:
    columns = sorted({c for row in table.values() for c in row})
    lines = ["| scenario | noise | " + " | ".join(columns) + " |",
             "|---|---|" + "---|" * len(columns)]
    means: dict[str, list[float]] = defaultdict(list)
    wins: dict[str, int] = defaultdict(int)
    for (scenario, noise), row in sorted(table.items()):
        values = {c: sum(row[c]) / len(row[c]) for c in columns if row.get(c)}
        best = max((v for c, v in values.items() if not c.startswith(PRIVILEGED)),
                   default=None)
        for column, value in values.items():
            means[column].append(value)
            wins[column] += value == best and not column.startswith(PRIVILEGED)
        lines.append(f"| {scenario} | {noise} | " + " | ".join(
            f"**{values[c]:.{digits}f}**" if values.get(c) == best else
            (f"{values[c]:.{digits}f}" if c in values else "-") for c in columns) + " |")
    lines.append("| **mean** | all | " + " | ".join(
        f"{sum(means[c]) / len(means[c]):.{digits}f}" for c in columns) + " |")
    lines.append("| best in | conditions | " + " | ".join(str(wins[c]) for c in columns) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", nargs="+", help="roco-env compare output folders")
    parser.add_argument("--digits", type=int, default=3, help="decimals of each mean")
    args = parser.parse_args()
    print(markdown(load(args.folders), args.digits))
