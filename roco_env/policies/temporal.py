"""Temporal smoothing of pose corrections across steps, around any alignment policy.

:class:`TemporalSmoothing` runs the inner policy every step and tracks, per
collaborator, its correction (dx m, dy m, dyaw rad; the action of one slot) with
a filterpy Kalman filter under a random-walk model (F = I, H = I). Filters are
keyed by (ego, collaborator): the ego from ``info["agent"]`` and the collaborator
by agent id from ``info["collaborators"]`` (so slot reordering does not mix
filters). One instance can therefore serve every agent of an env
(``{a: policy(obs[a], infos[a]) for a in env.agents}``); a call without those ids
is a ValueError (keyed by slot, the egos would share filters).

* A step where the inner policy applied a correction to a slot is a measurement
  (yaw innovation wrapped to (-pi, pi]); the filter's estimate is the output.
* A step where it did not (``last_result.applied`` False, or an all-zero action for
  policies without a result) inherits the last good estimate (predict only), for at
  most ``max_age`` steps; older filters are dropped and the inner action is used.

Helps when the true correction changes slowly (bias, drift, localisation noise)
and evidence is intermittent; it lags and hurts under i.i.d. per-step noise.
Call :meth:`reset` between episodes.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import Any

import numpy as np
from filterpy.kalman import KalmanFilter

from roco_env.policies.adapter import collaborator_keys
from roco_env.policies.base import AlignmentResult, PolicyWrapper, act
from roco_env.policies.landmarks import require_sigmas
from roco_env.schema import spec

__all__ = ["SmoothingParams", "TemporalSmoothing", "coalign_temporal", "roco_temporal"]


@dataclass(frozen=True)
class SmoothingParams:
    """The wrapper's own parameters: the Kalman filter's (module docstring)."""

    process_std: tuple[float, float, float] = spec(
        (0.05, 0.05, float(np.deg2rad(0.05))), doc="random-walk std per step (m, m, rad)")
    measurement_std: tuple[float, float, float] = spec(
        (0.05, 0.05, float(np.deg2rad(0.05))), doc="std of one inner correction (m, m, rad)")
    max_age: int = spec(20, low=0, doc="steps an estimate survives without a measurement")

    def __post_init__(self) -> None:
        require_sigmas(self.process_std, "process_std")
        require_sigmas(self.measurement_std, "measurement_std")


class TemporalSmoothing(PolicyWrapper):
    """``TemporalSmoothing(policy, **params)(obs, info=None) -> action (N, 3) float32``.

    policy: a policy name for ``make_policy`` or a callable (a plain function becomes a
    :class:`~roco_env.policies.base.Policy` through ``as_policy``); params: the fields of
    :class:`SmoothingParams`, and with a policy name the inner policy's parameters
    (policy_params, passed to make_policy). ``last_result``: the inner policy's.
    """

    # State kept across steps, per (ego, collaborator); ``roco-env list`` shows it.
    keeps_state = "per ego and collaborator (info['agent'], info['collaborators'])"

    def __init__(self, policy: str | Callable, **params: Any) -> None:
        super().__init__(policy, *self.own_params(SmoothingParams, params,
                                                  "temporal smoothing"))
        self.q = np.asarray(self.params.process_std)
        self.r = np.asarray(self.params.measurement_std)
        self.max_age = self.params.max_age
        self._filters: dict[Hashable, KalmanFilter] = {}
        self._age: dict[Hashable, int] = {}

    def reset(self) -> None:
        """Forget every filter (call between episodes) and reset the inner policy."""
        self._filters.clear()
        self._age.clear()
        super().reset()

    def _new_filter(self, z: np.ndarray) -> KalmanFilter:
        kf = KalmanFilter(dim_x=3, dim_z=3)
        kf.F, kf.H = np.eye(3), np.eye(3)
        kf.Q, kf.R = np.diag(self.q**2), np.diag(self.r**2)
        kf.x, kf.P = z.reshape(3, 1).copy(), np.diag(self.r**2)
        return kf

    @staticmethod
    def _applied(action: np.ndarray, result: AlignmentResult | None) -> np.ndarray:
        """Per slot, whether the inner call corrected it: its result's ``applied``, or for a
        call that reported no result, a nonzero action."""
        if result is not None and np.shape(result.applied) == (action.shape[0],):
            return np.asarray(result.applied, dtype=bool)
        return np.any(action != 0.0, axis=1)

    def __call__(self, observation: dict, info: dict | None = None) -> np.ndarray:
        filled = np.nonzero(np.asarray(observation["collab_mask"]) > 0)[0]
        keys = collaborator_keys(info, filled, "temporal smoothing")
        action, result = act(self.policy, observation, info)
        action = np.asarray(action, dtype=float).reshape(-1, 3)
        applied = self._applied(action, result)
        out = action.copy()
        for slot, key in zip(filled, keys, strict=True):
            kf = self._filters.get(key)
            if applied[slot]:
                if kf is None:
                    kf = self._filters[key] = self._new_filter(action[slot])
                else:
                    kf.predict()
                    z = action[slot].copy()
                    z[2] = kf.x[2, 0] + np.angle(
                        np.exp(1j * (z[2] - kf.x[2, 0]))
                    )  # wrapped innovation
                    kf.update(z)
                self._age[key] = 0
            elif kf is not None and self._age[key] < self.max_age:
                kf.predict()
                self._age[key] += 1
            else:
                self._filters.pop(key, None)
                self._age.pop(key, None)
                continue
            out[slot] = kf.x.reshape(3)
            out[slot, 2] = np.angle(np.exp(1j * out[slot, 2]))
        return out.astype(np.float32)


def roco_temporal(**params) -> TemporalSmoothing:
    """Registry factory: RoCo wrapped in :class:`TemporalSmoothing` (params split between
    the wrapper's own keywords and RoCo's)."""
    return TemporalSmoothing("roco", **params)


def coalign_temporal(**params) -> TemporalSmoothing:
    """Registry factory: CoAlign wrapped in :class:`TemporalSmoothing`."""
    return TemporalSmoothing("coalign", **params)
