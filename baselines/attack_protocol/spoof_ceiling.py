"""The information-theoretic ceiling of detecting a small pose spoof (docs/attacks.md).

    python baselines/attack_protocol/spoof_ceiling.py            # the protocol's settings
    python baselines/attack_protocol/spoof_ceiling.py --offset-m 3 --alpha 0.01

The best any detector can do on one ego's evidence: it knows the spoof's offset (its
direction and size at every step) and sees the true relative pose exactly (perfect box
alignment), so all it lacks is the reported pose's noise. Two agents each report with
Gaussian noise ``sigma_t`` m per axis, independent from step to step (the protocol's
noise model), so the relative pose's error along the offset's axis has variance
``2 sigma_t^2`` (the lever arm of the heading noise, ``(d sigma_r)^2`` across the sight
line, only adds to it: ``--lever-m d`` puts it on the offset's axis). After k steps with
offsets ``mu_1..mu_k`` m the Neyman-Pearson test (the log-likelihood ratio, a weighted
sum of the errors) at false-alarm rate ``alpha`` detects with probability
``Phi(sqrt(sum mu_j^2) / sigma - Phi^-1(1 - alpha))``. The share of steps detected is its
mean over the episode's steps, step 0 the first observation. That is the ceiling at the
same false-alarm rate on every step; a detector bound only by its mean false-alarm rate
over the episode (the protocol's "honest rejections" count) may spend more of it early,
where the evidence is weak: :func:`best_split` finds the per-step rates that maximise
the share detected (scipy's SLSQP), the ceiling under that rule. A drifting spoof
(``--drift-s``) lies by ``offset * min(1, t / drift)`` at ``t = step * dt``: nothing at
step 0.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

import numpy as np
from scipy.optimize import minimize
from scipy.stats import norm


def offsets(offset_m: float, steps: int, drift_s: float, dt: float) -> np.ndarray:
    """(steps,) the spoof's offset (m) at each step: fixed, or growing over ``drift_s``
    seconds from zero at step 0 (steps ``dt`` s apart)."""
    if drift_s == 0.0:
        return np.full(steps, offset_m)
    return offset_m * np.minimum(1.0, np.arange(steps) * dt / drift_s)


def detection_per_step(mu: np.ndarray, sigma: float, alpha: float) -> np.ndarray:
    """(steps,) the Neyman-Pearson detector's probability of detection at each step, on
    the steps so far (offsets ``mu`` m, noise std ``sigma`` m along the offset, false
    alarm ``alpha`` per step)."""
    strength = np.sqrt(np.cumsum(np.asarray(mu, dtype=float) ** 2)) / sigma
    return norm.cdf(strength - norm.isf(alpha))


def best_split(mu: np.ndarray, sigma: float, alpha: float) -> tuple[float, np.ndarray]:
    """The largest mean detection over the steps, and the per-step false-alarm rates
    (steps,) giving it, among rates whose mean is ``alpha`` (offsets ``mu`` m, noise std
    ``sigma`` m along the offset): the ceiling of a detector bound by its mean false-alarm
    rate over the episode."""
    strength = np.sqrt(np.cumsum(np.asarray(mu, dtype=float) ** 2)) / sigma
    steps = strength.shape[0]

    def missed(rates: np.ndarray) -> float:
        return -float(np.mean(norm.cdf(strength - norm.isf(np.clip(rates, 1e-12, 1.0)))))

    found = minimize(missed, np.full(steps, alpha), method="SLSQP",
                     bounds=[(0.0, 1.0)] * steps,
                     constraints=[{"type": "eq", "fun": lambda rates: np.mean(rates) - alpha}])
    if not found.success:
        raise RuntimeError(f"best_split: the optimiser did not converge: {found.message}")
    return -float(found.fun), found.x


def relative_sigma(sigma_t: float, sigma_r_deg: float, lever_m: float) -> float:
    """Std (m) of two agents' relative pose error along the offset's axis: each reports
    ``sigma_t`` m per axis; ``lever_m`` m of lever arm of the heading noise on that axis."""
    return float(np.sqrt(2.0 * sigma_t**2 + (lever_m * np.radians(sigma_r_deg)) ** 2))


def _check(args: argparse.Namespace) -> None:
    for name in ("offset_m", "sigma_t", "dt"):
        if not getattr(args, name) > 0.0:
            raise ValueError(f"--{name.replace('_', '-')} must be > 0; got {getattr(args, name)}")
    for name in ("sigma_r", "lever_m", "drift_s"):
        if not getattr(args, name) >= 0.0:
            raise ValueError(f"--{name.replace('_', '-')} must be >= 0; got {getattr(args, name)}")
    if not 0.0 < args.alpha < 1.0:
        raise ValueError(f"--alpha must lie in (0, 1); got {args.alpha}")
    if args.steps < 1:
        raise ValueError(f"--steps must be >= 1; got {args.steps}")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--offset-m", type=float, default=1.0, help="the spoof's offset, m")
    parser.add_argument("--drift-s", type=float, default=0.0,
                        help="seconds the offset takes to grow from zero (0: fixed)")
    parser.add_argument("--sigma-t", type=float, default=0.4, help="m per agent and axis")
    parser.add_argument("--sigma-r", type=float, default=0.4, help="deg per agent")
    parser.add_argument("--lever-m", type=float, default=0.0,
                        help="lever arm of the heading noise on the offset's axis, m")
    parser.add_argument("--alpha", type=float, default=0.02, help="false alarms per step")
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--dt", type=float, default=0.1, help="s between steps")
    args = parser.parse_args(argv)
    try:
        _check(args)
    except ValueError as exc:
        parser.error(str(exc))
    sigma = relative_sigma(args.sigma_t, args.sigma_r, args.lever_m)
    mu = offsets(args.offset_m, args.steps, args.drift_s, args.dt)
    power = detection_per_step(mu, sigma, args.alpha)
    print(f"offset {args.offset_m:g} m (drift {args.drift_s:g} s), relative noise "
          f"{sigma:.3f} m along it, false alarm {args.alpha:g} per step, {args.steps} steps")
    print("step  offset m  detected")
    for step, (m, p) in enumerate(zip(mu, power, strict=True)):
        print(f"{step:4d}  {m:8.2f}  {100 * p:7.1f} %")
    print(f"share of steps detected: {100 * power.mean():.1f} %")
    share, rates = best_split(mu, sigma, args.alpha)
    print(f"with the false alarms split over the steps (mean {args.alpha:g}; per step "
          f"{', '.join(f'{r:.4f}' for r in rates)}): {100 * share:.1f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
