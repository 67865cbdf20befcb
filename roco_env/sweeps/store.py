"""Append-only JSONL store of finished cells, the basis of resuming a sweep.

One JSON object per line, written with flush + fsync as each cell finishes, so a
killed sweep loses at most the cell being written. A torn last line (killed mid
write) is sealed with a newline before the next append. Lines that are not a
record (torn, edited, foreign) are skipped on reading and counted
(:attr:`ResultStore.unreadable`), so callers can report them.
Records carry ``key`` and ``status`` ("ok" or "error"); when a key appears more
than once (a failed cell retried later) the last record wins.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any


def _json_safe(value: Any) -> Any:
    """NaN/inf -> None so every line is strict JSON (readable by any parser)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value


class ResultStore:
    """Results file of one sweep (``results.jsonl``)."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self.unreadable = 0  # non-blank lines the last read could not use

    def records(self) -> list[dict]:
        """Every readable record in file order (others skipped, counted in ``unreadable``)."""
        self.unreadable = 0
        if not self.path.exists():
            return []
        records = []
        with self.path.open(encoding="utf-8", errors="replace") as handle:
            for line in handle:
                if not line.strip():
                    continue
                try:
                    record = json.loads(line)
                except json.JSONDecodeError:
                    record = None
                if isinstance(record, dict) and "key" in record and "status" in record:
                    records.append(record)
                else:
                    self.unreadable += 1
        return records

    def latest(self) -> dict[str, dict]:
        """key -> last record written for it."""
        return {record["key"]: record for record in self.records()}

    def completed_keys(self) -> set[str]:
        """Keys whose latest record succeeded (skipped on resume; failed ones are retried)."""
        return {key for key, record in self.latest().items() if record["status"] == "ok"}

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
