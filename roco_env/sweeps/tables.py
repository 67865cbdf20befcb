"""Markdown tables of summary rows: the paper's Table 1 shape, pose errors, crowding.

AP values are printed in percent with one decimal; ``n/a`` marks a setting with
no data (NaN: no GT and no prediction) and ``err`` one whose every seed failed.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

from roco_env.sweeps.aggregate import SummaryRow
from roco_env.sweeps.spec import format_scalar


def noise_label(noise: float) -> str:
    """The paper's "sigma_t/sigma_r" column label, e.g. ``0.4/0.4``."""
    return f"{noise:.1f}/{noise:.1f}" if round(noise, 1) == noise else f"{noise:g}/{noise:g}"


def density_label(density: float | None) -> str:
    return "default" if density is None else format_scalar(float(density))


def _cell(row: SummaryRow | None, key: str, scale: float = 100.0, digits: int = 1) -> str:
    if row is None:
        return "-"
    if not row.seeds:
        return "err"
    value = row.metrics.get(key, math.nan)
    return "n/a" if not math.isfinite(value) else f"{value * scale:.{digits}f}"


def markdown_table(header: Sequence[str], body: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(cells) + " |" for cells in body]
    return "\n".join(lines)


def _ordered(values: list) -> list:
    """Distinct values in first-seen order."""
    return list(dict.fromkeys(values))


def _matrix(rows: Sequence[SummaryRow], column: Callable[[SummaryRow], object], key: str,
            first: str, label: Callable[[object], str]) -> str:
    policies = _ordered([r.policy for r in rows])
    columns = sorted(_ordered([column(r) for r in rows]), key=lambda c: (c is None, c or 0.0))
    index = {(r.policy, column(r)): r for r in rows}
    body = [[p] + [_cell(index.get((p, c)), key) for c in columns] for p in policies]
    return markdown_table([first] + [label(c) for c in columns], body)


def ap_by_noise(rows: Sequence[SummaryRow], key: str) -> str:
    """Table 1 block: rows = policies, columns = noise levels, values = ``key`` in %."""
    return _matrix(rows, lambda r: r.noise, key, "Policy \\ noise (m/deg)", noise_label)


def ap_by_density(rows: Sequence[SummaryRow], key: str) -> str:
    """Crowding block: rows = policies, columns = densities, values = ``key`` in %."""
    return _matrix(rows, lambda r: r.density, key, "Policy \\ density", density_label)


POSE_HEADER = ("Policy", "Noise", "RPE t med / p95 (m)", "RPE r med / p95 (deg)",
               "before: t med / p95 (m)", "before: r med / p95 (deg)", "Success@1m1deg (%)",
               "Success@2m2deg (%)", "Success@3m3deg (%)", "Match P (%)", "Match R (%)",
               "Corrected (%)", "Warm time per call (ms)")


def pose_table(rows: Sequence[SummaryRow]) -> str:
    """RPE (pooled median / 95th percentile) and success, matching, correction share and
    the time of one warm policy call (median per episode leaving out each agent's first
    call, which pays numba's compilation; mean over seeds)."""
    body = []
    for row in sorted(rows, key=lambda r: r.noise):  # stable: policies keep their order
        pair = [f"{_cell(row, a, 1.0, 3)} / {_cell(row, b, 1.0, 3)}" for a, b in (
            ("rpe_t_median", "rpe_t_p95"), ("rpe_r_median", "rpe_r_p95"),
            ("rpe_t_median_before", "rpe_t_p95_before"),
            ("rpe_r_median_before", "rpe_r_p95_before"))]
        shares = [_cell(row, k) for k in ("success1", "success2", "success3",
                                          "match_precision", "match_recall",
                                          "correction_share")]
        body.append([row.policy, noise_label(row.noise), *pair, *shares,
                     _cell(row, "time_per_call_ms", 1.0, 2)])
    return markdown_table(POSE_HEADER, body)
