"""The record stored per finished cell (one JSONL line; see :mod:`roco_env.sweeps.store`).

``{"key", "cell", "version", "status": "ok" | "error", "elapsed_s",
   "time_per_call_ms", "metrics": {...}, "samples": {"before": [[t m, r deg], ...],
   "after": [...]}}`` for a success; an error record has ``"error"`` ("Type: message")
and ``"traceback"`` (the last frames) instead of metrics and samples. The wall times
(:data:`WALL_TIME_FIELDS`: the cell's ``elapsed_s`` and ``time_per_call_ms``, the
median wall time of one warm policy call, see :mod:`roco_env.sweeps.episode`) are kept
out of ``metrics``, which a rerun reproduces exactly.

:func:`record_problem` checks a record read back from a file against this schema
(:class:`RecordMetrics` declares every metric with its allowed range, and
:class:`RecordCell` every field of the cell, through :mod:`roco_env.schema`); the
store skips a record that fails it like a torn line.
"""

from __future__ import annotations

import traceback
from dataclasses import dataclass
from typing import Any

import numpy as np

from roco_env.schema import ConfigError, build, spec
from roco_env.sweeps.cells import Cell

RECORD_VERSION = 1
TRACEBACK_FRAMES = 6
WALL_TIME_FIELDS = ("elapsed_s", "time_per_call_ms")  # the fields that differ between reruns
REQUIRED_METRICS = ("ap30", "ap50", "ap70")  # what every report reads


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


def _share(doc: str = "") -> Any:
    """A metric in [0, 1]; null where it is undefined (NaN when computed, e.g. AP with
    no ground truth and no prediction)."""
    return spec(None, low=0.0, high=1.0, doc=doc)


def _error(unit: str) -> Any:
    return spec(None, low=0.0, doc=f"relative pose error, {unit}; null without samples")


def _count() -> Any:
    return spec(None, low=0)


@dataclass
class RecordMetrics:
    """An ``ok`` record's ``metrics`` (see :class:`roco_env.sweeps.episode.EpisodeScorer`):
    shares in [0, 1], pose errors in m / deg (>= 0), counts >= 0; null (NaN when written)
    where a metric is undefined. Only :data:`REQUIRED_METRICS` must be present."""

    ap30: float | None = _share("dataset AP at IoU 0.3")
    ap50: float | None = _share()
    ap70: float | None = _share()
    rpe_t_median: float | None = _error("m")
    rpe_t_p95: float | None = _error("m")
    rpe_r_median: float | None = _error("deg")
    rpe_r_p95: float | None = _error("deg")
    rpe_t_median_before: float | None = _error("m")
    rpe_t_p95_before: float | None = _error("m")
    rpe_r_median_before: float | None = _error("deg")
    rpe_r_p95_before: float | None = _error("deg")
    success1: float | None = _share()
    success2: float | None = _share()
    success3: float | None = _share()
    success1_before: float | None = _share()
    success2_before: float | None = _share()
    success3_before: float | None = _share()
    worse_share: float | None = _share("pairs whose correction added > 0.5 m of translation "
                                       "error")
    match_precision: float | None = _share()
    match_recall: float | None = _share()
    correction_share: float | None = _share()
    bytes_received: float | None = spec(None, low=0.0, doc="bytes an agent received per step "
                                        "(the network stage on), mean")
    frames: int | None = _count()
    decisions: int | None = _count()
    matched_frames: int | None = _count()
    pairs: int | None = _count()
    steps: int | None = _count()
    # cells under attack (roco_env.sweeps.attack): over the honest egos
    ap70_clean: float | None = _share("dataset AP@0.7 of the same egos without the attack")
    attack_success: float | None = _share("ego-steps whose AP@0.7 fell by > 5 points")
    detection_rate: float | None = _share("attackers' slots rejected")
    honest_rejected: float | None = _share("honest collaborators' slots rejected")
    clean_rejected: float | None = _share("the same without the attack")


@dataclass
class RecordHead:
    """The fields every record has, and the wall times."""

    key: str = spec("")
    cell: dict = spec({})
    version: int = spec(RECORD_VERSION, choices=(RECORD_VERSION,))
    status: str = spec("ok", choices=("ok", "error"))
    elapsed_s: float = spec(0.0, low=0.0)
    time_per_call_ms: float | None = spec(None, low=0.0)
    provenance: str = spec("")
    error: str = spec("")
    traceback: str = spec("")
    metrics: dict = spec({})
    samples: dict = spec({})


@dataclass
class RecordCell:
    """A record's ``cell`` (:meth:`roco_env.sweeps.cells.Cell.to_dict`): noise level s
    (sigma_t = s m, sigma_r = s deg), env steps, traffic density (null = the scenario's)."""

    scenario: str = spec("")
    noise: float = spec(0.0, low=0.0)
    policy: str = spec("")
    seed: int = spec(0, low=0)
    steps: int = spec(1, low=1)
    density: float | None = spec(None, low=0.0)
    overrides: dict = spec({})


def _check_cell(record: dict) -> None:
    missing = [f for f in ("scenario", "noise", "policy", "seed", "steps")
               if isinstance(record["cell"], dict) and f not in record["cell"]]
    if missing:
        raise ConfigError(f"cell without {', '.join(missing)}")
    build(RecordCell, record["cell"], "record", "cell.")
    try:
        key = Cell.from_dict(record["cell"]).key
    except (TypeError, ValueError) as exc:  # e.g. an override value that is a list
        raise ConfigError(f"cell: {exc}") from exc
    if key != record["key"]:
        raise ConfigError(f"key {record['key']!r} is not the key of its cell ({key!r})")


def _check_samples(samples: dict) -> None:
    """``before`` / ``after``: lists of [t m, r deg] rows, finite and >= 0."""
    for which in ("before", "after"):
        if which not in samples:
            raise ConfigError(f"samples.{which} is missing")
        try:
            rows = np.asarray(samples[which], dtype=float)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"samples.{which} must be [t, r] number pairs: {exc}") from exc
        if rows.size and (rows.ndim != 2 or rows.shape[1] != 2):
            raise ConfigError(f"samples.{which} must be [t, r] pairs; got shape {rows.shape}")
        if not (np.isfinite(rows).all() and (rows >= 0).all()):
            raise ConfigError(f"samples.{which} must be finite and >= 0")


def _check(record: Any) -> None:
    if not isinstance(record, dict):
        raise ConfigError(f"not a JSON object but {type(record).__name__}")
    required = ("key", "cell", "status", "elapsed_s") + (
        ("metrics", "samples") if record.get("status") == "ok" else ("error",))
    missing = [name for name in required if name not in record]
    if missing:
        raise ConfigError(f"missing {', '.join(missing)}")
    build(RecordHead, record, "record")
    _check_cell(record)
    if record["status"] == "ok":
        absent = [name for name in REQUIRED_METRICS if name not in record["metrics"]]
        if absent:
            raise ConfigError(f"metrics without {', '.join(absent)}")
        build(RecordMetrics, record["metrics"], "record", "metrics.")
        _check_samples(record["samples"])


def record_problem(record: Any) -> str | None:
    """Why ``record`` (a parsed line) is not a valid record, or None when it is one."""
    try:
        _check(record)
    except ConfigError as exc:
        return str(exc).removeprefix("record: ")
    return None
