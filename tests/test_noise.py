"""Pose-noise models (roco_env.noise): reproducibility, stated moments, temporal structure."""

from __future__ import annotations

import math

import numpy as np
import pytest

from roco_env.geometry import wrap_angle
from roco_env.noise import make_pose_noise
from roco_env.scenario import NoiseConfig
from roco_env.stages import available_stages

MODELS = available_stages("noise")

SIGMA_T, SIGMA_R = 0.4, 0.6  # m, deg


def agents(n: int) -> list[str]:
    return [f"cav_{k}" for k in range(n)]


def run_errors(model: str, n_agents: int, n_steps: int, seed: int = 0, dt: float = 0.1,
               speed: float = 0.0, **config) -> np.ndarray:
    """Errors (steps, agents, 3) [m, m, deg] of reported minus true poses over one episode."""
    config = {"sigma_t": SIGMA_T, "sigma_r": SIGMA_R, **config}
    noise = make_pose_noise(NoiseConfig(model=model, **config), agents(n_agents), dt)
    rng = np.random.default_rng(seed)
    noise.reset(rng)
    truth = np.zeros((n_agents, 3))
    truth[:, 2] = np.linspace(-np.pi, np.pi, n_agents, endpoint=False)
    errors = []
    for _ in range(n_steps):
        reported = noise.perturb(truth, rng)
        error = reported - truth
        error[:, 2] = np.degrees(wrap_angle(error[:, 2]))
        errors.append(error)
        # Agents drive forward along their heading while turning slowly.
        truth = truth.copy()
        truth[:, 0] += speed * dt * np.cos(truth[:, 2])
        truth[:, 1] += speed * dt * np.sin(truth[:, 2])
        truth[:, 2] = wrap_angle(truth[:, 2] + 0.02)
    return np.array(errors)


def assert_std(samples: np.ndarray, expected: float) -> None:
    assert np.std(samples) == pytest.approx(expected, rel=0.03)


@pytest.mark.parametrize("model", MODELS)
def test_seeded_reproducibility(model):
    first = run_errors(model, 3, 30, seed=7, speed=10.0)
    again = run_errors(model, 3, 30, seed=7, speed=10.0)
    other = run_errors(model, 3, 30, seed=8, speed=10.0)
    np.testing.assert_array_equal(first, again)
    assert not np.allclose(first, other)


@pytest.mark.parametrize("model", MODELS)
def test_reported_yaw_is_wrapped_and_zero_sigma_is_exact(model):
    errors = run_errors(model, 4, 20, sigma_t=0.0, sigma_r=0.0, speed=5.0)
    np.testing.assert_allclose(errors, 0.0, atol=1e-6)
    noise = make_pose_noise(NoiseConfig(model=model, sigma_r=20.0), agents(50), 0.1)
    rng = np.random.default_rng(1)
    noise.reset(rng)
    reported = noise.perturb(np.tile([0.0, 0.0, np.pi], (50, 1)), rng)
    assert np.all((reported[:, 2] > -np.pi) & (reported[:, 2] <= np.pi))


def test_gaussian_moments_100k_draws():
    errors = run_errors("gaussian", 1000, 100)  # 100k draws per axis
    for axis, sigma in ((0, SIGMA_T), (1, SIGMA_T), (2, SIGMA_R)):
        assert_std(errors[..., axis], sigma)
        assert abs(errors[..., axis].mean()) < 0.01 * sigma * 3
    # i.i.d. over steps
    assert abs(np.corrcoef(errors[1:, :, 0].ravel(), errors[:-1, :, 0].ravel())[0, 1]) < 0.02


def test_laplace_scale_is_sigma_100k_draws():
    errors = run_errors("laplace", 1000, 100)
    for axis, sigma in ((0, SIGMA_T), (1, SIGMA_T), (2, SIGMA_R)):
        assert_std(errors[..., axis], math.sqrt(2.0) * sigma)  # scale b = sigma
        assert np.mean(np.abs(errors[..., axis])) == pytest.approx(sigma, rel=0.03)


def test_bias_constant_within_episode_and_redrawn_after_reset():
    errors = run_errors("bias", 20000, 5, speed=3.0)  # 100k draws over 5 steps x 20k agents
    np.testing.assert_allclose(errors, np.broadcast_to(errors[0], errors.shape), atol=1e-9)
    assert_std(errors[0, :, :2], SIGMA_T)
    assert_std(errors[0, :, 2], SIGMA_R)
    noise = make_pose_noise(NoiseConfig(model="bias"), agents(3), 0.1)
    rng = np.random.default_rng(0)
    noise.reset(rng)
    first = noise.perturb(np.zeros((3, 3)), rng)
    noise.reset(rng)
    assert not np.allclose(first, noise.perturb(np.zeros((3, 3)), rng))


def test_ar1_stationary_std_and_autocorrelation():
    rho = 0.8
    errors = run_errors("ar1", 5000, 40, params={"rho": rho})
    assert_std(errors[0, :, :2], SIGMA_T)  # 10k draws, stationary from the first step
    assert_std(errors[-20:, :, 0], SIGMA_T)  # 100k draws late in the episode
    assert_std(errors[-20:, :, 2], SIGMA_R)
    for lag in (1, 3):
        corr = np.corrcoef(errors[lag:, :, 0].ravel(), errors[:-lag, :, 0].ravel())[0, 1]
        assert corr == pytest.approx(rho**lag, abs=0.015)


def test_drift_variance_grows_linearly_in_time():
    dt = 0.1
    errors = run_errors("drift", 20000, 40, dt=dt)
    std_1s = errors[9, :, :2]  # after 10 steps = 1 s
    assert_std(std_1s, SIGMA_T)
    assert_std(errors[9, :, 2], SIGMA_R)
    assert_std(errors[39, :, :2], 2.0 * SIGMA_T)  # 4 s -> sqrt(4) sigma
    # The increments are independent: correlation of e(1 s) and e(4 s) is sqrt(1/4).
    corr = np.corrcoef(errors[9, :, 0], errors[39, :, 0])[0, 1]
    assert corr == pytest.approx(0.5, abs=0.03)
    # dt-independent: the same std after 1 s with a 0.05 s step.
    assert_std(run_errors("drift", 20000, 20, dt=0.05)[19, :, :2], SIGMA_T)


def test_localization_error_correlated_and_bounded():
    errors = run_errors("localization", 6, 1500, speed=12.0, dt=0.1)  # 150 s at 12 m/s
    position = errors[..., :2]
    lag1 = np.corrcoef(position[1:].ravel(), position[:-1].ravel())[0, 1]
    assert lag1 > 0.8  # temporally correlated, unlike i.i.d. noise
    assert np.max(np.abs(position)) < 6.0 * SIGMA_T  # GNSS keeps it bounded
    first, second = np.std(position[:750]), np.std(position[750:])
    assert 0.5 < second / first < 2.0  # no drift away over time
    assert 0.2 * SIGMA_T < np.std(position) < 1.5 * SIGMA_T


def test_localization_gnss_every_step_beats_raw_fix():
    errors = run_errors("localization", 50, 200, speed=10.0,
                        params={"gnss_rate": 10.0, "dropout": 0.0})
    assert np.std(errors[50:, :, :2]) < SIGMA_T  # filtering averages the fixes
    assert np.std(errors[50:, :, 2]) < SIGMA_R


def test_localization_dropout_lets_the_error_grow_between_fixes():
    always = run_errors("localization", 40, 400, speed=10.0, params={"dropout": 0.0})
    often_lost = run_errors("localization", 40, 400, speed=10.0, params={"dropout": 0.9})
    assert np.std(often_lost[..., :2]) > np.std(always[..., :2])


def test_per_agent_levels():
    config = {"per_agent": {"cav_1": [2.0, 0.0]}}
    errors = run_errors("gaussian", 3, 40000, **config)
    assert_std(errors[:, 0, :2], SIGMA_T)
    assert_std(errors[:, 1, :2], 2.0)
    np.testing.assert_array_equal(errors[:, 1, 2], 0.0)
    assert_std(errors[:, 2, 2], SIGMA_R)
    loc = run_errors("localization", 2, 300, speed=5.0,
                     per_agent={"cav_0": [0.0, 0.0]}, params={"gnss_sigma": 1.0})
    np.testing.assert_allclose(loc[:, 0], 0.0, atol=1e-6)
    assert np.std(loc[:, 1, :2]) > 0.1


def test_perturb_ego_flag_is_carried_for_the_env():
    noise = make_pose_noise(NoiseConfig(perturb_ego=False), agents(2), 0.1)
    assert noise.perturb_ego is False
    rng = np.random.default_rng(0)
    noise.reset(rng)
    assert not np.allclose(noise.perturb(np.zeros((2, 3)), rng), 0.0)  # still noisy for all


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"config": NoiseConfig(model="uniform")}, "noise.model.*gaussian"),
        ({"config": NoiseConfig(sigma_t=-1.0)}, "noise.sigma_t"),
        ({"config": NoiseConfig(sigma_r=float("nan"))}, "noise.sigma_r"),
        ({"config": NoiseConfig(model="ar1", params={"rho": 1.0})}, "noise.params.rho"),
        ({"config": NoiseConfig(model="ar1", params={"alpha": 1.0})}, "noise.params.*rho"),
        ({"config": NoiseConfig(params={"rho": 0.5})}, "noise.params"),
        ({"config": NoiseConfig(model="localization", params={"dropout": 1.0})}, "dropout"),
        ({"config": NoiseConfig(model="localization", params={"gnss_rate": 0})}, "gnss_rate"),
        ({"config": NoiseConfig(model="localization", params={"gnss_sigma": "x"})}, "gnss_sigma"),
        ({"config": NoiseConfig(per_agent={"rsu_9": [1, 1]})}, "noise.per_agent.*cav_0"),
        ({"config": NoiseConfig(per_agent={"cav_0": [1]})}, "noise.per_agent"),
        ({"config": NoiseConfig(per_agent={"cav_0": [1, -2]})}, "noise.per_agent"),
        ({"dt": 0.0}, "dt"),
        ({"agent_ids": ["a", "a"]}, "agent_ids"),
    ],
)
def test_bad_config_raises_value_error(kwargs, match):
    args = {"config": NoiseConfig(), "agent_ids": agents(2), "dt": 0.1, **kwargs}
    with pytest.raises(ValueError, match=match):
        make_pose_noise(**args)


def test_bad_perturb_input_raises_value_error():
    noise = make_pose_noise(NoiseConfig(), agents(2), 0.1)
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="rng"):
        noise.reset(np.random.RandomState(0))
    noise.reset(rng)
    with pytest.raises(ValueError, match="true_poses"):
        noise.perturb(np.zeros((3, 3)), rng)
    with pytest.raises(ValueError, match="true_poses"):
        noise.perturb(np.full((2, 3), np.nan), rng)
    with pytest.raises(ValueError, match="rng"):
        noise.perturb(np.zeros((2, 3)), 0)
