"""Small NaN-aware summaries shared by the episode scorer and the seed aggregation."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from roco_env.metrics import success_rate

SUCCESS_THRESHOLDS = (1, 2, 3)  # Success@lambda m lambda deg


def _finite(values: Sequence[float]) -> np.ndarray:
    arr = np.asarray(values, dtype=float).reshape(-1)
    return arr[np.isfinite(arr)]


def nanmean(values: Sequence[float]) -> float:
    """Mean of the finite values; NaN when there are none."""
    arr = _finite(values)
    return float(arr.mean()) if arr.size else float("nan")


def nanstd(values: Sequence[float]) -> float:
    """Population std of the finite values; NaN when there are none."""
    arr = _finite(values)
    return float(arr.std()) if arr.size else float("nan")


def _percentiles(samples: np.ndarray, suffix: str) -> dict[str, float]:
    out = {}
    for column, unit in ((0, "t"), (1, "r")):
        values = samples[:, column]
        for name, q in (("median", 50.0), ("p95", 95.0)):
            value = float(np.percentile(values, q)) if values.size else float("nan")
            out[f"rpe_{unit}_{name}{suffix}"] = value
    return out


WORSE_BY_M = 0.5  # a correction that adds more than this to the translation error made it worse


def pose_error_summary(before: np.ndarray, after: np.ndarray) -> dict[str, float]:
    """RPE median/p95 and Success@1m1deg / @2m2deg / @3m3deg before and after correction,
    and the share of pairs whose correction made the translation error more than
    :data:`WORSE_BY_M` m worse than the reported pose's.

    ``before``/``after``: (P, 2) finite rows [translation m, rotation deg], row k of both
    the same pair. Keys: ``rpe_t_median`` (m), ``rpe_r_p95`` (deg), ``success1``, ... and
    the same with a ``_before`` suffix, and ``worse_share``. NaN where there are no samples.
    """
    before = np.asarray(before, dtype=float).reshape(-1, 2)
    after = np.asarray(after, dtype=float).reshape(-1, 2)
    out = _percentiles(before, "_before")
    out.update(_percentiles(after, ""))
    out["worse_share"] = float(np.mean(after[:, 0] - before[:, 0] > WORSE_BY_M)) \
        if after.shape[0] and after.shape == before.shape else float("nan")
    for lam in SUCCESS_THRESHOLDS:
        out[f"success{lam}_before"] = success_rate(np.reshape(before, (-1, 2)), lam)
        out[f"success{lam}"] = success_rate(np.reshape(after, (-1, 2)), lam)
    return out
