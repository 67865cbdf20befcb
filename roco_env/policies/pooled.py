"""Pooled significance: RoCo's do-no-harm test decided over a collaborator's history.

RoCo keeps a collaborator's reported pose when one frame's matched boxes cannot show
that it is wrong beyond the estimation noise (the Wald statistic W of the correction,
chi-square with 3 dof when the reported pose is right; :mod:`roco_env.policies.roco`).
That protects clean poses, but small real errors (a few tenths of a metre or a
degree) stay uncorrected in the frames where W falls short, while an aligner
without the test corrects them. A localisation error is a property of the agent and
its sensors, not of one frame: over the last ``window`` frames with a test, the sum
of W is chi-square with 3 n dof if that collaborator's reported relative poses are
right. When that pooled test rejects at ``level`` (``chi2.sf(sum W, 3 n) < 1 -
level``), its reported poses are known to carry errors, and the frame's own test is
waived: the correction is applied (RoCo's other checks, the number of matches and of
inlier edges, still hold). Clean poses keep the frame-by-frame test, since their
pooled statistic stays at its null. The statistics keep being recorded while the test is
waived, so the decision follows the data if the errors go away.
"""

from __future__ import annotations

import numbers
from collections import deque
from collections.abc import Hashable, Sequence

import numpy as np
from scipy.stats import chi2

__all__ = ["PooledSignificance"]


class PooledSignificance:
    """Per-collaborator history of significance statistics and the pooled test on it.

    level: confidence of the pooled test, in (0, 1); window: frames of history per
    collaborator (>= 1); min_frames: frames needed before the pooled test may waive
    (1 <= min_frames <= window). Keys are any hashables (the policy uses
    (ego, collaborator) ids).
    """

    def __init__(self, level: float, window: int = 20, min_frames: int = 3) -> None:
        if isinstance(level, bool) or not isinstance(level, numbers.Real) or not 0 < level < 1:
            raise ValueError("pooled_significance must be None (off) or in (0, 1); got "
                             f"{level!r}")
        if not 1 <= min_frames <= window:
            raise ValueError(f"need 1 <= min_frames <= window; got {min_frames}, {window}")
        self.level, self.window, self.min_frames = float(level), window, min_frames
        self._history: dict[Hashable, deque[float]] = {}

    def waived(self, key: Hashable) -> bool:
        """Whether the pooled test says this collaborator's reported poses carry errors."""
        history = self._history.get(key)
        if history is None or len(history) < self.min_frames:
            return False
        return bool(chi2.sf(sum(history), 3 * len(history)) < 1.0 - self.level)

    def record(self, keys: Sequence[Hashable], statistics: Sequence[float]) -> None:
        """Add one frame's statistics (NaN: not tested, skipped) under their keys."""
        for key, statistic in zip(keys, statistics, strict=True):
            if np.isfinite(statistic):
                self._history.setdefault(key, deque(maxlen=self.window)).append(float(statistic))

    def reset(self) -> None:
        """Forget every history (call between episodes)."""
        self._history.clear()
