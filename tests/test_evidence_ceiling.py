"""baselines/attack_protocol/evidence_ceiling.py: the Neyman-Pearson ceiling of detecting
ghosts, erased objects and the consistent spoof, closed form against a simulation of the
same detector, and its evidence on a protocol episode."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import norm

PATH = Path(__file__).resolve().parents[1] / "baselines" / "attack_protocol" / "evidence_ceiling.py"
_SPEC = importlib.util.spec_from_file_location("evidence_ceiling", PATH)
ceiling = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(ceiling)


@pytest.mark.parametrize("strength", [0.0, 1.5])
def test_the_closed_form_is_the_simulated_detectors_rate(strength):
    """Three pieces of evidence an honest witness would have seen with probability r
    (0.5, 0.6, 0.7: all three missed with p0 = 0.06) and a Gaussian measurement: the test
    that rejects when all three are missed and the measurement exceeds the
    ``alpha / p0`` quantile (seeded, 200,000 draws each way) has false-alarm rate alpha
    and detects as often as ``np_power`` says; the Gaussian test alone, at alpha,
    detects less."""
    rng = np.random.default_rng(0)
    r, alpha, n = np.array([0.5, 0.6, 0.7]), 0.02, 200_000
    p0 = float(np.prod(1.0 - r))
    threshold = norm.isf(alpha / p0)
    honest_missed = (rng.random((n, 3)) >= r).all(axis=1)
    false_alarm = np.mean(honest_missed & (rng.normal(0.0, 1.0, n) > threshold))
    detected = np.mean(rng.normal(strength, 1.0, n) > threshold)  # attacked: all missed
    assert false_alarm == pytest.approx(alpha, abs=0.002)
    assert detected == pytest.approx(float(ceiling.np_power(strength, p0, alpha)), abs=0.005)
    assert ceiling.np_power(strength, p0, alpha) > norm.cdf(strength - norm.isf(alpha))


def test_without_a_measurement_the_ceiling_is_alpha_over_p0():
    power = ceiling.np_power(np.zeros(3), np.array([1.0, 0.1, 0.01]), 0.02)
    np.testing.assert_allclose(power, [0.02, 0.2, 1.0])


def test_pooling_the_false_alarms_spends_them_on_the_strongest_evidence():
    """Four items, evidence only from misses (p0 0.01, 0.03, 0.5, 1), a mean rate of 0.02:
    the budget 0.08 covers the first two wholly and 0.04 / 0.5 of the third (0.52 mean);
    the Lagrangian solution reaches it to within that fractional item, above the flat
    rate's 0.43."""
    p0 = np.array([0.01, 0.03, 0.5, 1.0])
    flat = ceiling.np_power(np.zeros(4), p0, 0.02).mean()
    pooled = ceiling.pooled_power(np.zeros(4), p0, 0.02)
    assert flat == pytest.approx((1 + 2 / 3 + 0.04 + 0.02) / 4)
    assert 0.5 - 1e-6 <= pooled <= 0.52 + 1e-6
    assert pooled > flat


def test_ghost_evidence_on_a_protocol_episode():
    """urban_intersection, ghosts 5, seed 0, two steps: four honest egos each step, the
    evidence only misses (no measurement), each ego's p0 falling over the steps."""
    strength, p0 = ceiling.attack_items("urban_intersection", "ghosts 5", [0], 2, 0.566,
                                        0.0, 2.0)
    assert strength.shape == (8,) and not strength.any()
    assert np.all((p0 > 0.0) & (p0 < 1.0))
    assert np.all(p0[4:] <= p0[:4])


@pytest.mark.parametrize("argv, field", [(["--alpha", "0"], "--alpha"),
                                         (["--attacks", "spoof 1 m"], "--attacks"),
                                         (["--scenes", "nowhere"], "--scenes"),
                                         (["--near-m", "-1"], "--near-m")])
def test_bad_options_are_refused_naming_them(argv, field, capsys):
    with pytest.raises(SystemExit):
        ceiling.main(argv)
    assert field in capsys.readouterr().err
