"""Pose-noise models: what each agent *reports* as its world pose (docs/conventions.md).

Every model adds an error to the true world pose ``(x, y, yaw)`` of every agent
(the ego included, CoAlign protocol), in the world frame; yaw is wrapped to
(-pi, pi]. Levels ``sigma_t`` (m) and ``sigma_r`` (DEGREES) are standard
deviations per axis; ``per_agent`` (agent id -> [sigma_t, sigma_r]) overrides
them for single agents. Models (``NoiseConfig.model``):

* ``gaussian`` (default): i.i.d. per step, N(0, sigma_t) on x and y, N(0, sigma_r) on yaw.
* ``laplace``: i.i.d. per step, Laplace with **scale b = sigma** (as CoAlign's
  code does), so the per-axis std is sqrt(2) * sigma.
* ``bias``: one Gaussian draw per agent and episode (at the first ``perturb``
  after ``reset``), constant for the rest of the episode.
* ``drift``: Gaussian random walk starting at zero, increments
  N(0, sigma * sqrt(dt / 1 s)), so the std after 1 s of simulated time is sigma
  (and grows like sqrt(t)).
* ``ar1``: e_k = rho e_{k-1} + sqrt(1 - rho^2) sigma z_k, z_k ~ N(0, 1), started
  from the stationary law, so the std is sigma at every step and the lag-1
  autocorrelation is rho (per step). Param ``rho`` in [0, 1), default 0.9.
* ``localization``: each agent's reported pose is the estimate of a filterpy
  Kalman filter (state x, y, yaw) fed with noisy odometry every step (true body-
  frame motion increment plus noise, rotated into the world with the *estimated*
  heading) and noisy GNSS position/heading fixes at ``gnss_rate`` Hz, each fix
  lost with probability ``dropout``. The first fix after reset is never lost
  and initialises the filter. Params: ``gnss_sigma`` (m, default the agent's
  sigma_t), ``heading_sigma`` (deg, default the agent's sigma_r), ``gnss_rate``
  (Hz, default 1.0), ``dropout`` (default 0.05), ``odom_sigma_t`` (m per
  sqrt(s), default 0.5 * gnss_sigma) and ``odom_sigma_r`` (deg per sqrt(s),
  default 0.5 * heading_sigma); per-step odometry noise is these times
  sqrt(dt). A per_agent entry replaces that agent's gnss/heading sigmas. With
  all sigmas zero the poses are exact. The error is temporally correlated and
  stays bounded (GNSS pulls the estimate back).

``perturb`` always returns noisy poses for all agents. ``perturb_ego=False`` is
carried as :attr:`PoseNoise.perturb_ego` and applied by the environment, which
then uses each ego's *true* pose as its own reported pose (its collaborators'
poses stay noisy). Every random draw comes from the generator passed in.
"""

from __future__ import annotations

import abc
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from roco_env.geometry import se2_relative, wrap_angle
from roco_env.scenario import NoiseConfig
from roco_env.schema import build, spec
from roco_env.stages import available_stages, checked_params, stage

if TYPE_CHECKING:  # filterpy loads with the first localization filter, not with every env
    from filterpy.kalman import KalmanFilter

__all__ = ["AR1Params", "LocalizationParams", "PoseNoise", "make_pose_noise"]


@dataclass
class AR1Params:
    """``ar1`` noise: the error's lag-1 autocorrelation per step."""

    rho: float = spec(0.9, low=0.0, high=1.0, high_open=True, doc="autocorrelation per step")


@dataclass
class LocalizationParams:
    """``localization`` noise: a Kalman filter fed with GNSS fixes and odometry."""

    gnss_sigma: float | None = spec(None, low=0.0, high=100.0,
                                    doc="GNSS position std, m; null = the agent's sigma_t")
    heading_sigma: float | None = spec(None, low=0.0, high=180.0,
                                       doc="GNSS heading std, deg; null = the agent's sigma_r")
    gnss_rate: float = spec(1.0, low=0.0, high=100.0, low_open=True, doc="GNSS fixes per s, Hz")
    dropout: float = spec(0.05, low=0.0, high=1.0, high_open=True,
                          doc="probability that a fix is lost")
    odom_sigma_t: float | None = spec(None, low=0.0, high=100.0,
                                      doc="odometry std, m per sqrt(s); null = gnss_sigma / 2")
    odom_sigma_r: float | None = spec(None, low=0.0, high=180.0,
                                      doc="odometry std, deg per sqrt(s); null = heading_sigma / 2")


# Variance floor (m^2, rad^2) keeping the Kalman filter invertible at zero noise.
_MIN_VARIANCE = 1e-18


class PoseNoise(abc.ABC):
    """Base pose-noise model; subclasses implement :meth:`_report`.

    Attributes: ``agent_ids`` (A,), ``dt`` (s), ``std`` (A, 3) per-agent standard
    deviations of (x m, y m, yaw rad), ``perturb_ego`` (applied by the env).
    """

    model = "base"

    @classmethod
    def from_config(cls, config: NoiseConfig, agent_ids: tuple[str, ...],
                    dt: float) -> PoseNoise:
        """The stage factory (roco_env.stages): the model at ``config``'s levels."""
        return cls(agent_ids, dt, _std(_levels(config, agent_ids)), config.perturb_ego)

    def __init__(self, agent_ids: Sequence[str], dt: float, std: np.ndarray,
                 perturb_ego: bool = True) -> None:
        self.agent_ids = tuple(agent_ids)
        self.dt = float(dt)
        self.std = np.asarray(std, dtype=float).reshape(len(self.agent_ids), 3)
        self.perturb_ego = bool(perturb_ego)
        self._steps = 0
        self._reset_state()

    def reset(self, rng: np.random.Generator) -> None:
        """Start a new episode (stateful models forget their state)."""
        _check_rng(rng)
        self._steps = 0
        self._reset_state()

    def perturb(self, true_poses: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Reported world poses (A, 3) for the true ones (A, 3); call once per step."""
        _check_rng(rng)
        poses = np.asarray(true_poses, dtype=float)
        if poses.shape != (len(self.agent_ids), 3):
            raise ValueError(
                f"true_poses must have shape ({len(self.agent_ids)}, 3) = one (x, y, yaw) per "
                f"agent; got {poses.shape}"
            )
        if not np.all(np.isfinite(poses)):
            raise ValueError("true_poses contains NaN or inf; all values must be finite")
        reported = self._report(poses, rng)
        self._steps += 1
        reported[:, 2] = wrap_angle(reported[:, 2])
        return reported

    def _reset_state(self) -> None:
        """Forget per-episode state; stateless models have none."""
        return None

    @abc.abstractmethod
    def _report(self, poses: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Reported poses (A, 3) for validated true poses (A, 3); yaw wrapped afterwards."""

    def _gaussian(self, rng: np.random.Generator) -> np.ndarray:
        return rng.standard_normal(self.std.shape) * self.std


class AdditiveNoise(PoseNoise):
    """Reported pose = true pose + an error drawn by :meth:`_error` (world frame)."""

    def _report(self, poses: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        return poses + self._error(rng)

    @abc.abstractmethod
    def _error(self, rng: np.random.Generator) -> np.ndarray:
        """Error (A, 3) of this step."""


class GaussianNoise(AdditiveNoise):
    """I.i.d. Gaussian error every step."""

    model = "gaussian"

    def _error(self, rng: np.random.Generator) -> np.ndarray:
        return self._gaussian(rng)


class LaplaceNoise(AdditiveNoise):
    """I.i.d. Laplace error every step, scale b = sigma (std sqrt(2) sigma)."""

    model = "laplace"

    def _error(self, rng: np.random.Generator) -> np.ndarray:
        return rng.laplace(0.0, 1.0, self.std.shape) * self.std


class StatefulNoise(AdditiveNoise):
    """An error that evolves from step to step; ``_next`` maps the previous error
    (None at the first step of an episode) to the new one."""

    def _reset_state(self) -> None:
        self._offset: np.ndarray | None = None

    def _error(self, rng: np.random.Generator) -> np.ndarray:
        self._offset = self._next(self._offset, rng)
        return self._offset

    @abc.abstractmethod
    def _next(self, previous: np.ndarray | None, rng: np.random.Generator) -> np.ndarray:
        """The new error (A, 3) given the previous one."""


class BiasNoise(StatefulNoise):
    """Constant Gaussian offset per agent and episode."""

    model = "bias"

    def _next(self, previous: np.ndarray | None, rng: np.random.Generator) -> np.ndarray:
        return self._gaussian(rng) if previous is None else previous


class DriftNoise(StatefulNoise):
    """Random walk from zero; std sigma after 1 s, growing like sqrt(t)."""

    model = "drift"

    def _next(self, previous: np.ndarray | None, rng: np.random.Generator) -> np.ndarray:
        step = self._gaussian(rng) * math.sqrt(self.dt)  # dt in seconds, per 1 s
        return step if previous is None else previous + step


class AR1Noise(StatefulNoise):
    """Stationary first-order autoregressive error, std sigma, lag-1 correlation rho."""

    model = "ar1"

    def __init__(self, agent_ids: Sequence[str], dt: float, std: np.ndarray,
                 perturb_ego: bool = True, *, rho: float) -> None:
        super().__init__(agent_ids, dt, std, perturb_ego)
        self.rho = rho

    @classmethod
    def from_config(cls, config: NoiseConfig, agent_ids: tuple[str, ...],
                    dt: float) -> AR1Noise:
        params = build(AR1Params, dict(config.params), where="noise", prefix="noise.params.")
        return cls(agent_ids, dt, _std(_levels(config, agent_ids)), config.perturb_ego,
                   rho=params.rho)

    def _next(self, previous: np.ndarray | None, rng: np.random.Generator) -> np.ndarray:
        fresh = self._gaussian(rng)
        if previous is None:
            return fresh
        return self.rho * previous + math.sqrt(1.0 - self.rho**2) * fresh


class LocalizationNoise(PoseNoise):
    """Per-agent Kalman filter fusing noisy odometry with intermittent GNSS fixes.

    ``gnss_std`` and ``odom_std`` are (A, 3) standard deviations of (x m, y m,
    yaw rad); odom_std is per sqrt(second).
    """

    model = "localization"

    def __init__(self, agent_ids: Sequence[str], dt: float, gnss_std: np.ndarray,
                 odom_std: np.ndarray, perturb_ego: bool = True, *, gnss_rate: float,
                 dropout: float) -> None:
        super().__init__(agent_ids, dt, gnss_std, perturb_ego)
        self.odom_step_std = np.asarray(odom_std, dtype=float).reshape(self.std.shape) * math.sqrt(
            self.dt
        )
        self.fix_every = max(1, round(1.0 / (gnss_rate * self.dt)))
        self.dropout = dropout

    @classmethod
    def from_config(cls, config: NoiseConfig, agent_ids: tuple[str, ...],
                    dt: float) -> LocalizationNoise:
        """Precedence of the GNSS sigmas: per_agent entry > params > the global levels."""
        params = build(LocalizationParams, dict(config.params), where="noise",
                       prefix="noise.params.")
        levels = _levels(config, agent_ids)
        per_agent = config.per_agent or {}
        gnss = levels.copy()
        for column, value in enumerate((params.gnss_sigma, params.heading_sigma)):
            if value is not None:
                gnss[[a not in per_agent for a in agent_ids], column] = value
        odom = 0.5 * gnss
        for column, value in enumerate((params.odom_sigma_t, params.odom_sigma_r)):
            if value is not None:
                odom[:, column] = value
        return cls(agent_ids, dt, _std(gnss), _std(odom), config.perturb_ego,
                   gnss_rate=params.gnss_rate, dropout=params.dropout)

    def _reset_state(self) -> None:
        self._filters: list[KalmanFilter] = []
        self._previous: np.ndarray | None = None

    def _report(self, poses: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        fix = poses + self._gaussian(rng)
        if self._previous is None:
            self._filters = [self._new_filter(k, fix[k]) for k in range(len(self.agent_ids))]
        else:
            motion = se2_relative(self._previous, poses)  # true body-frame increments (A, 3)
            odometry = motion + rng.standard_normal(motion.shape) * self.odom_step_std
            has_fix = self._steps % self.fix_every == 0
            lost = rng.random(len(self.agent_ids)) < self.dropout
            for k, kf in enumerate(self._filters):
                self._predict(kf, odometry[k])
                if has_fix and not lost[k]:
                    # Innovation of the heading taken the short way round the circle.
                    z = fix[k].copy()
                    z[2] = kf.x[2, 0] + wrap_angle(z[2] - kf.x[2, 0])
                    kf.update(z)
                kf.x[2, 0] = wrap_angle(kf.x[2, 0])
        self._previous = poses.copy()
        return np.stack([kf.x[:, 0] for kf in self._filters])

    def _new_filter(self, k: int, first_fix: np.ndarray) -> KalmanFilter:
        from filterpy.kalman import KalmanFilter

        kf = KalmanFilter(dim_x=3, dim_z=3)
        kf.x = first_fix.reshape(3, 1).copy()
        kf.R = np.diag(np.maximum(self.std[k] ** 2, _MIN_VARIANCE))
        kf.P = kf.R.copy()
        kf.Q = np.diag(np.maximum(self.odom_step_std[k] ** 2, _MIN_VARIANCE))
        kf.H = np.eye(3)
        kf.F = np.eye(3)
        kf.B = np.eye(3)
        return kf

    @staticmethod
    def _predict(kf: KalmanFilter, odometry: np.ndarray) -> None:
        """Dead-reckon: body-frame increment rotated by the estimated heading."""
        c, s = math.cos(kf.x[2, 0]), math.sin(kf.x[2, 0])
        world = np.array([c * odometry[0] - s * odometry[1], s * odometry[0] + c * odometry[1],
                          odometry[2]])
        kf.predict(u=world.reshape(3, 1))


def _check_rng(rng: Any) -> None:
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"rng must be a numpy.random.Generator; got {type(rng).__name__}")


def _non_negative(value: Any, name: str) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        number = float("nan")
    if not (math.isfinite(number) and number >= 0.0):
        raise ValueError(f"{name} must be a finite number >= 0; got {value!r}")
    return number


def _levels(config: NoiseConfig, agent_ids: Sequence[str]) -> np.ndarray:
    """Per-agent (sigma_t m, sigma_r deg) (A, 2), per_agent entries overriding the levels."""
    base = (_non_negative(config.sigma_t, "noise.sigma_t"),
            _non_negative(config.sigma_r, "noise.sigma_r"))
    per_agent: Mapping[str, Any] = config.per_agent or {}
    if not isinstance(per_agent, Mapping):
        raise ValueError(f"noise.per_agent must map agent id -> [sigma_t, sigma_r]; got {per_agent!r}")
    unknown = sorted(set(per_agent) - set(agent_ids))
    if unknown:
        raise ValueError(f"noise.per_agent has unknown agent ids {unknown}; allowed: {list(agent_ids)}")
    levels = np.tile(np.asarray(base), (len(agent_ids), 1))
    for k, agent in enumerate(agent_ids):
        if agent in per_agent:
            pair = per_agent[agent]
            if not isinstance(pair, Sequence) or isinstance(pair, str) or len(pair) != 2:
                raise ValueError(
                    f"noise.per_agent[{agent!r}] must be [sigma_t m, sigma_r deg]; got {pair!r}"
                )
            levels[k] = [_non_negative(pair[0], f"noise.per_agent[{agent!r}][0] (sigma_t)"),
                         _non_negative(pair[1], f"noise.per_agent[{agent!r}][1] (sigma_r)")]
    return levels


def _std(levels: np.ndarray) -> np.ndarray:
    """(A, 2) [m, deg] -> (A, 3) [m, m, rad]."""
    return np.stack([levels[:, 0], levels[:, 0], np.radians(levels[:, 1])], axis=1)


def make_pose_noise(config: NoiseConfig, agent_ids: Sequence[str], dt: float) -> PoseNoise:
    """Build the pose-noise model of ``config`` (the stage ``config.model`` names) for
    ``agent_ids`` stepping every ``dt`` s."""
    if config.model not in available_stages("noise"):
        raise ValueError(f"noise.model must be one of {list(available_stages('noise'))}; "
                         f"got {config.model!r}")
    agent_ids = tuple(agent_ids)
    if len(set(agent_ids)) != len(agent_ids):
        raise ValueError(f"agent_ids must be unique; got {list(agent_ids)}")
    if _non_negative(dt, "dt") == 0.0:
        raise ValueError(f"dt must be a finite number of seconds > 0; got {dt!r}")
    checked_params("noise", config.model, config.params, where="noise")
    return stage("noise", config.model).load_factory()(config, agent_ids, dt)
