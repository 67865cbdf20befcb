"""Markdown tables of summary rows: the paper's Table 1 shape, pose errors, crowding, AP
against a grid axis (any scenario field a sweep varies).

AP values are printed in percent with one decimal; ``n/a`` marks a setting with
no data (NaN: no GT and no prediction) and ``err`` one whose every seed failed.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

from roco_env.sweeps.aggregate import SummaryRow
from roco_env.sweeps.text_specs import format_scalar


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


def is_number(value: object) -> bool:
    """A real number (bools are not)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def value_order(value: object) -> tuple:
    """Sort key of an axis value: numbers ascending, then other values by their text,
    None last."""
    return (value is None, not is_number(value), value if is_number(value) else str(value))


def axis_label(value: object) -> str:
    """A grid axis value as its column label (``null`` for None)."""
    return "null" if value is None else format_scalar(value)


def grid_axes(rows: Sequence[SummaryRow]) -> list[str]:
    """The overrides the rows vary (the sweep's grid axes), in first-seen order."""
    keys = _ordered([k for r in rows for k in r.overrides])
    return [k for k in keys if len({axis_label(r.overrides.get(k)) for r in rows}) > 1]


def _matrix(rows: Sequence[SummaryRow], column: Callable[[SummaryRow], object], key: str,
            first: str, label: Callable[[object], str], scale: float = 100.0,
            digits: int = 1) -> str:
    policies = _ordered([r.policy for r in rows])
    columns = sorted(_ordered([column(r) for r in rows]), key=value_order)
    index = {(r.policy, column(r)): r for r in rows}
    body = [[p] + [_cell(index.get((p, c)), key, scale, digits) for c in columns]
            for p in policies]
    return markdown_table([first] + [label(c) for c in columns], body)


def ap_by_noise(rows: Sequence[SummaryRow], key: str) -> str:
    """Table 1 block: rows = policies, columns = noise levels, values = ``key`` in %."""
    return _matrix(rows, lambda r: r.noise, key, "Policy \\ noise (m/deg)", noise_label)


def ap_by_density(rows: Sequence[SummaryRow], key: str) -> str:
    """Crowding block: rows = policies, columns = densities, values = ``key`` in %."""
    return _matrix(rows, lambda r: r.density, key, "Policy \\ density", density_label)


def ap_by_axis(rows: Sequence[SummaryRow], axis: str, key: str, scale: float = 100.0,
               digits: int = 1) -> str:
    """Grid-axis block: rows = policies, columns = the values of override ``axis``, values
    = ``key`` times ``scale`` (default: a share in %)."""
    return _matrix(rows, lambda r: r.overrides.get(axis), key, f"Policy \\ {axis}", axis_label,
                   scale, digits)


POSE_HEADER = ("Policy", "Noise", "RPE t med / p95 (m)", "RPE r med / p95 (deg)",
               "before: t med / p95 (m)", "before: r med / p95 (deg)", "Success@1m1deg (%)",
               "Success@2m2deg (%)", "Success@3m3deg (%)", "Worse by > 0.5 m (%)",
               "Match P (%)", "Match R (%)", "Corrected (%)", "Warm time per call (ms)")


def pose_table(rows: Sequence[SummaryRow], axes: Sequence[str] = ()) -> str:
    """RPE (pooled median / 95th percentile) and success, the share of pairs the correction
    made more than 0.5 m worse, matching, correction share and the time of one warm policy
    call (median per episode leaving out each agent's first call, which pays numba's
    compilation; mean over seeds). ``axes``: grid axes, a column each after the noise."""
    body = []
    for row in sorted(rows, key=lambda r: (r.noise, *(value_order(r.overrides.get(a))
                                                        for a in axes))):  # policies keep order
        pair = [f"{_cell(row, a, 1.0, 3)} / {_cell(row, b, 1.0, 3)}" for a, b in (
            ("rpe_t_median", "rpe_t_p95"), ("rpe_r_median", "rpe_r_p95"),
            ("rpe_t_median_before", "rpe_t_p95_before"),
            ("rpe_r_median_before", "rpe_r_p95_before"))]
        shares = [_cell(row, k) for k in ("success1", "success2", "success3", "worse_share",
                                          "match_precision", "match_recall",
                                          "correction_share")]
        body.append([row.policy, noise_label(row.noise),
                     *(axis_label(row.overrides.get(a)) for a in axes), *pair, *shares,
                     _cell(row, "time_per_call_ms", 1.0, 2)])
    return markdown_table([*POSE_HEADER[:2], *axes, *POSE_HEADER[2:]], body)
