"""The record stored per finished cell (one JSONL line; see :mod:`roco_env.sweeps.store`).

``{"key", "cell", "version", "status": "ok" | "error", "elapsed_s",
   "time_per_call_ms", "metrics": {...}, "samples": {"before": [[t m, r deg], ...],
   "after": [...]}}`` for a success; an error record has ``"error"`` ("Type: message")
and ``"traceback"`` (the last frames) instead of metrics and samples. The wall times
(:data:`WALL_TIME_FIELDS`: the cell's ``elapsed_s`` and the mean ``time_per_call_ms``
of one policy call) are kept out of ``metrics``, which a rerun reproduces exactly.
"""

from __future__ import annotations

import traceback
from typing import Any

from roco_env.sweeps.grid import Cell

RECORD_VERSION = 1
TRACEBACK_FRAMES = 6
WALL_TIME_FIELDS = ("elapsed_s", "time_per_call_ms")  # the fields that differ between reruns


def ok_record(cell: Cell, metrics: dict, samples: dict, elapsed_s: float,
              time_per_call_ms: float | None = None) -> dict[str, Any]:
    record = {"key": cell.key, "cell": cell.to_dict(), "version": RECORD_VERSION,
              "status": "ok", "metrics": metrics, "samples": samples,
              "elapsed_s": round(elapsed_s, 3)}
    if time_per_call_ms is not None:
        record["time_per_call_ms"] = round(time_per_call_ms, 3)
    return record


def error_record(cell: Cell, exc: BaseException, elapsed_s: float) -> dict[str, Any]:
    """Record of a cell that raised ``exc`` (call inside the ``except`` block)."""
    summary = "".join(traceback.format_exception(exc, limit=-TRACEBACK_FRAMES))
    return {"key": cell.key, "cell": cell.to_dict(), "version": RECORD_VERSION,
            "status": "error", "error": f"{type(exc).__name__}: {exc}",
            "traceback": summary, "elapsed_s": round(elapsed_s, 3)}
