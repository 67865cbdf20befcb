"""Append-only JSONL store of finished cells, the basis of resuming a sweep.

One JSON object per line, written with flush + fsync as each cell finishes, so a
killed sweep loses at most the cell being written. A torn last line (killed mid
write) is sealed with a newline before the next append. Lines that are not a
valid record (torn, edited, foreign: not JSON, or failing the record schema of
:func:`roco_env.sweeps.records.record_problem`, e.g. ``"ap70": "high"``, ``5.0``
or ``NaN``, or no ``metrics``) are skipped on reading and counted
(:attr:`ResultStore.unreadable`, their line numbers and reasons in
:attr:`ResultStore.skipped`), so callers can report them and the sweep recomputes
their cells.
Records carry ``key`` and ``status`` ("ok" or "error"); when a key appears more
than once (a failed cell retried later) the last record wins.

One sweep at a time writes a results file: :meth:`ResultStore.exclusive` holds an
advisory lock (``fcntl.flock``) on ``<results file>.lock`` beside it, and a second
sweep into the same folder stops with :class:`ResultsInUse`. The lock belongs to the
open file, so it ends with the process however it ends (a killed sweep leaves no stale
lock; the lock file stays, holding the last sweep's pid). Platforms without ``fcntl``
(Windows) run unlocked.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

try:
    import fcntl
except ImportError:  # Windows
    fcntl = None  # type: ignore[assignment]

from roco_env.sweeps.records import record_problem


def _json_safe(value: Any) -> Any:
    """NaN/inf -> None so every line is strict JSON (readable by any parser)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value


class ResultsInUse(RuntimeError):
    """Another sweep is writing the results file (it holds the lock)."""


class ResultStore:
    """Results file of one sweep (``results.jsonl``)."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self.skipped: list[tuple[int, str]] = []  # (line number from 1, why) of the last read

    @property
    def unreadable(self) -> int:
        """Non-blank lines the last read could not use."""
        return len(self.skipped)

    def skipped_text(self, shown: int = 10) -> str:
        """``results.jsonl: N unreadable line(s) skipped (line 3: metrics.ap70 ...; ...)``."""
        reasons = "; ".join(f"line {number}: {why}" for number, why in self.skipped[:shown])
        more = f"; and {self.unreadable - shown} more" if self.unreadable > shown else ""
        return f"{self.path}: {self.unreadable} unreadable line(s) skipped ({reasons}{more})"

    def records(self) -> list[dict]:
        """Every valid record in file order (others skipped, listed in ``skipped``)."""
        self.skipped = []
        if not self.path.exists():
            return []
        records = []
        with self.path.open(encoding="utf-8", errors="replace") as handle:
            for number, line in enumerate(handle, start=1):
                if not line.strip():
                    continue
                try:
                    record = json.loads(line)
                except json.JSONDecodeError as exc:
                    problem: str | None = f"not JSON ({exc.msg})"
                else:
                    problem = record_problem(record)
                if problem is None:
                    records.append(record)
                else:
                    self.skipped.append((number, problem))
        return records

    def latest(self) -> dict[str, dict]:
        """key -> last record written for it."""
        return {record["key"]: record for record in self.records()}

    def completed_keys(self) -> set[str]:
        """Keys whose latest record succeeded (skipped on resume; failed ones are retried)."""
        return {key for key, record in self.latest().items() if record["status"] == "ok"}

    @contextmanager
    def exclusive(self) -> Iterator[None]:
        """Hold the results file's lock for the block; :class:`ResultsInUse` naming the file
        and the holder's pid when another process holds it."""
        lock_path = self.path.with_name(self.path.name + ".lock")
        lock_path.parent.mkdir(parents=True, exist_ok=True)
        with lock_path.open("a+", encoding="utf-8") as handle:
            if fcntl is not None:
                try:
                    fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:
                    handle.seek(0)
                    holder = handle.read().strip() or "unknown"
                    raise ResultsInUse(
                        f"{self.path} is being written by another sweep (pid {holder}); wait "
                        "for it to finish or choose another output folder") from None
                handle.truncate(0)
                handle.write(f"{os.getpid()}\n")
                handle.flush()
            yield

    def append(self, record: dict) -> None:
        """Write one record as a line and make it durable before returning."""
        line = json.dumps(_json_safe(record), allow_nan=False, sort_keys=True)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with self.path.open("a+b") as handle:
            if handle.tell() > 0:
                handle.seek(-1, os.SEEK_END)
                if handle.read(1) != b"\n":  # seal a line torn by a kill
                    handle.write(b"\n")
            handle.write(line.encode("utf-8") + b"\n")
            handle.flush()
            os.fsync(handle.fileno())

    def select(self, keys: Iterable[str]) -> list[dict]:
        """Latest records of ``keys`` in the given order (keys without a record omitted)."""
        latest = self.latest()
        return [latest[key] for key in keys if key in latest]
