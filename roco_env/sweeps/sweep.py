"""Run a grid of cells into a results file, resuming where a previous run stopped.

A cell whose latest record in the file is ``ok`` *and* carries the provenance the
current code computes for it (:mod:`roco_env.sweeps.provenance`) is reused; the
rest (new, previously failed, or stale: produced by other code, input files or scenario
content) run on the chosen backend and each record is appended as soon as it
arrives. Stale records and unreadable lines (torn, or failing the record schema:
their cells run again) are counted and said on stderr, the lines by number. A tqdm bar
shows progress and the failure count.

SIGTERM (like Ctrl-C) stops the sweep: the workers are stopped with it, finished
cells stay in the file and :class:`SweepStopped` is raised, so the same call
later resumes.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from collections.abc import Iterator, Sequence
from contextlib import closing, contextmanager
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from roco_env.sweeps.backends import CellFn, run_cells
from roco_env.sweeps.cells import Cell
from roco_env.sweeps.episode import run_cell
from roco_env.sweeps.provenance import Provenance
from roco_env.sweeps.store import ResultStore


class SweepStopped(KeyboardInterrupt):
    """The sweep was stopped by SIGINT or SIGTERM; finished cells are in the results file."""

    def __init__(self, signal_name: str, results_path: Path) -> None:
        super().__init__(signal_name)
        self.signal_name = signal_name
        self.results_path = results_path


@dataclass
class SweepOutcome:
    """Records of the grid's cells (grid order) and what this run did.

    stale: cells whose earlier ``ok`` record was produced by other code, input files or scenario
    content and were recomputed; unreadable: lines of the results file that are not
    valid records (skipped; their cells recomputed).
    """

    records: list[dict]
    ran: int
    skipped: int
    failed: int
    stale: int = 0
    unreadable: int = 0


@dataclass
class StoredResults:
    """The current records of a results file (any cell) and what was left out."""

    records: list[dict]
    stale: int
    unreadable: int


def stored_results(results_path: str | os.PathLike,
                   provenance: Provenance | None = None) -> StoredResults:
    """Latest record of every cell in the file whose provenance is current (for reports)."""
    store = ResultStore(results_path)
    latest = store.latest()
    provenance = provenance or Provenance()
    current = [r for r in latest.values() if provenance.current(r)]
    return StoredResults(current, len(latest) - len(current), store.unreadable)


@contextmanager
def _stop_on_signals(results_path: Path) -> Iterator[None]:
    """Turn SIGTERM and SIGINT into :class:`SweepStopped` while the sweep runs (main thread)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum: int, _frame: object) -> None:
        for sig in previous:  # let the clean-up (stopping the workers) finish
            signal.signal(sig, signal.SIG_IGN)
        raise SweepStopped(signal.Signals(signum).name, results_path)

    previous = {s: signal.signal(s, stop) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def run_sweep(
    cells: Sequence[Cell],
    results_path: str | os.PathLike,
    backend: str = "local",
    workers: int | None = None,
    address: str | None = None,
    cell_fn: CellFn = run_cell,
    progress: bool = True,
    provenance: Provenance | None = None,
) -> SweepOutcome:
    """Run the cells not yet (currently) finished in ``results_path``; every cell's record.

    ``provenance``: pass the one the caller also reports with (hashing the package once).
    Raises :class:`roco_env.sweeps.store.ResultsInUse` when another sweep is writing
    ``results_path`` (two sweeps would run every cell twice).
    """
    store = ResultStore(results_path)
    with store.exclusive():  # one sweep at a time writes the file
        provenance = provenance or Provenance()
        unique = list({cell.key: cell for cell in cells}.values())
        fingerprints = {cell.key: provenance.of(cell) for cell in unique}
        latest = store.latest()
        unreadable = store.unreadable
        ok = {cell.key for cell in unique
              if latest.get(cell.key, {}).get("status") == "ok"}
        reusable = {key for key in ok if latest[key].get("provenance") == fingerprints[key]}
        stale = len(ok) - len(reusable)
        if unreadable:
            print(store.skipped_text(), file=sys.stderr)
        if stale:
            print(f"{store.path}: {stale} cell(s) recomputed: their results were produced by "
                  "other code, scenario content or input files (weights, replay labels)",
                  file=sys.stderr)
        pending = [cell for cell in unique if cell.key not in reusable]
        failed = 0
        with _stop_on_signals(store.path), tqdm(
                total=len(unique), initial=len(unique) - len(pending), unit="cell", desc="sweep",
                disable=not progress, dynamic_ncols=True) as bar, closing(
                run_cells(pending, cell_fn, backend, workers, address)) as results:
            for cell, record in results:
                store.append({**record, "provenance": fingerprints[cell.key]})
                failed += record["status"] != "ok"
                bar.update(1)
                bar.set_postfix(failed=failed, refresh=False)
        return SweepOutcome(records=store.select(c.key for c in unique), ran=len(pending),
                            skipped=len(unique) - len(pending), failed=failed, stale=stale,
                            unreadable=unreadable)
