"""Run a grid of cells into a results file, resuming where a previous run stopped.

Cells whose latest record in the file is ``ok`` are skipped; the rest (new or
previously failed) run on the chosen backend and each record is appended as soon
as it arrives. A tqdm bar shows progress and the failure count.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass

from tqdm import tqdm

from roco_env.bench.backends import CellFn, run_cells
from roco_env.bench.episode import run_cell
from roco_env.bench.grid import Cell
from roco_env.bench.store import ResultStore


@dataclass
class SweepOutcome:
    """Records of the grid's cells (grid order) and what this run did."""

    records: list[dict]
    ran: int
    skipped: int
    failed: int


def run_sweep(
    cells: Sequence[Cell],
    results_path: str | os.PathLike,
    backend: str = "local",
    workers: int | None = None,
    address: str | None = None,
    cell_fn: CellFn = run_cell,
    progress: bool = True,
) -> SweepOutcome:
    """Run the cells not yet finished in ``results_path`` and return every cell's record."""
    store = ResultStore(results_path)
    unique = list({cell.key: cell for cell in cells}.values())
    done = store.completed_keys()
    pending = [cell for cell in unique if cell.key not in done]
    failed = 0
    with tqdm(total=len(unique), initial=len(unique) - len(pending), unit="cell",
              desc="sweep", disable=not progress, dynamic_ncols=True) as bar:
        for _, record in run_cells(pending, cell_fn, backend, workers, address):
            store.append(record)
            failed += record["status"] != "ok"
            bar.update(1)
            bar.set_postfix(failed=failed, refresh=False)
    return SweepOutcome(records=store.select(c.key for c in unique), ran=len(pending),
                        skipped=len(unique) - len(pending), failed=failed)
