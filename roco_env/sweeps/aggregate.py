"""Combine cell records over seeds into one summary row per setting.

A setting is a cell without its seed (scenario, density, noise, policy, steps,
overrides). Per setting: AP@0.3/0.5/0.7 = mean over seeds of each episode's
dataset AP (and the std of AP@0.7); RPE median/p95 and Success@1/@2/@3 are
computed on the pooled samples of all seeds (so the tail is not averaged away);
matching precision/recall, the correction share, the bytes received per step (the
network stage on; NaN without) and the time per policy call (each
episode's median warm call, see :mod:`roco_env.sweeps.episode`) are means over
seeds; ``steps_played`` is the fewest env steps a seed's episode played (below
``steps`` when a replay's frames ran out).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from roco_env.sweeps.stats import nanmean, nanstd, pose_error_summary

AP_KEYS = ("ap30", "ap50", "ap70")
MEAN_KEYS = ("match_precision", "match_recall", "correction_share", "bytes_received")


@dataclass
class SummaryRow:
    """One setting's numbers (AP in [0, 1], RPE in m / deg, shares in [0, 1])."""

    scenario: str
    density: float | None
    noise: float
    policy: str
    steps: int
    overrides: dict
    seeds: int
    failed: int
    metrics: dict[str, float] = field(default_factory=dict)
    before: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    after: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))

    def flat(self) -> dict:
        """Plain dict for CSV/JSON (no samples; each override a column of its own)."""
        return {"scenario": self.scenario, "density": self.density, "noise": self.noise,
                "policy": self.policy, "steps": self.steps, "seeds": self.seeds,
                "failed": self.failed, **self.overrides, **self.metrics}


def _value(metrics: dict, key: str) -> float:
    value = metrics.get(key)
    return float("nan") if value is None else float(value)


def _setting(cell: dict) -> tuple:
    overrides = tuple(sorted(cell.get("overrides", {}).items()))
    return (cell["scenario"], cell.get("density"), float(cell["noise"]), cell["policy"],
            int(cell["steps"]), overrides)


def _samples(records: list[dict], which: str) -> np.ndarray:
    parts = [np.asarray(r["samples"][which], dtype=float).reshape(-1, 2) for r in records]
    return np.concatenate(parts) if parts else np.zeros((0, 2))


def summarize(records: Iterable[dict]) -> list[SummaryRow]:
    """Summary rows in first-seen order of the records (grid order); failed seeds counted apart."""
    groups: dict[tuple, list[dict]] = {}
    for record in records:
        groups.setdefault(_setting(record["cell"]), []).append(record)
    rows = []
    for (scenario, density, noise, policy, steps, overrides), group in groups.items():
        ok = [r for r in group if r["status"] == "ok"]
        row = SummaryRow(scenario, density, noise, policy, steps, dict(overrides),
                         seeds=len(ok), failed=len(group) - len(ok))
        if ok:
            row.before, row.after = _samples(ok, "before"), _samples(ok, "after")
            metrics = {k: nanmean([_value(r["metrics"], k) for r in ok]) for k in AP_KEYS}
            metrics["ap70_std"] = nanstd([_value(r["metrics"], "ap70") for r in ok])
            metrics.update(pose_error_summary(row.before, row.after))
            metrics.update({k: nanmean([_value(r["metrics"], k) for r in ok]) for k in MEAN_KEYS})
            metrics["time_per_call_ms"] = nanmean([_value(r, "time_per_call_ms") for r in ok])
            # fewest env steps an episode played (records from before it was kept: the asked)
            metrics["steps_played"] = min(int(r["metrics"].get("steps", steps)) for r in ok)
            row.metrics = metrics
        rows.append(row)
    return rows
