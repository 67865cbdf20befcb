"""The learned attacker paid against its clean twin (``twin_reward``) and the held-out
evaluations that answer the issue's question (roco_env.training.rl.attacker_eval)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from roco_env.schema import ConfigError
from roco_env.training.rl.attacker import AttackerEnv, AttackerTrainConfig, main
from roco_env.training.rl.attacker_eval import STEALTH, best_stealthy, evaluate

LIE = np.array([1, 1, 1, 0, 0, -1], np.float32)  # a 3 m, 3 deg pose lie, its ghost off


def make(twin_reward: bool, victims: str = "identity") -> AttackerEnv:
    return AttackerEnv("urban_intersection", victims, {"ghosts": 1}, 0.4, 3, cavs=2, rsus=1,
                       twin_reward=twin_reward)


def returns(env: AttackerEnv, action: np.ndarray, seed: int = 0) -> list[float]:
    env.reset(seed=seed)
    rewards, done = [], False
    while not done:
        _, reward, terminated, truncated, _ = env.step(action)
        rewards.append(reward)
        done = terminated or truncated
    return rewards


def test_the_zero_action_that_hurts_no_victim_earns_zero_against_the_twin():
    env = make(True)
    zero = returns(env, np.zeros(6, np.float32))
    assert len(zero) == 3 and zero == pytest.approx([0.0] * 3, abs=1e-12)
    assert evaluate(env, lambda o: np.zeros(6, np.float32), [0])["ap70_clean"] > 0.0  # no trivial 0


def test_the_twin_reward_is_the_attacks_own_plus_the_twins_ap_of_the_same_victims():
    twin, own = make(True), make(False)
    paid, plain = returns(twin, LIE), returns(own, LIE)
    clean = twin.clean_log(0)
    victims = sorted(twin.log.egos - twin.log.attackers)
    expected = [np.mean([clean.ap70[agent, step] for agent in victims]) for step in (1, 2, 3)]
    assert np.array(paid) - np.array(plain) == pytest.approx(expected, abs=1e-12)
    assert paid[0] == pytest.approx(0.0, abs=1e-12)  # an action shapes the next frame on
    assert sum(paid) > 0.0  # the lie removes AP (test_train_attacker: evaluated too)


def test_evaluate_reports_the_points_removed_and_their_spread():
    env = make(False)
    one = evaluate(env, lambda o: LIE, [0])
    assert one["removed"] == pytest.approx(100.0 * (one["ap70_clean"] - one["ap70"]))
    assert one["removed"] > 0.0 and np.isnan(one["removed_sd"])
    two = evaluate(env, lambda o: np.zeros(6, np.float32), [0, 1])
    assert two["removed"] == 0.0 and two["removed_sd"] == 0.0


def test_the_best_stealthy_evaluation_is_the_most_removed_under_the_detection_limit():
    rows = [{"timesteps": 0, "removed": 0.5, "detection_rate": 0.0},
            {"timesteps": 1, "removed": 9.0, "detection_rate": STEALTH},  # not under it
            {"timesteps": 2, "removed": 3.0, "detection_rate": 0.09},
            {"timesteps": 3, "removed": 3.0, "detection_rate": 0.01},  # equal: the earlier
            {"timesteps": 4, "removed": 8.0, "detection_rate": float("nan")}]  # no decision
    assert best_stealthy(rows)["timesteps"] == 2
    assert best_stealthy(rows[1:2]) is None and best_stealthy([]) is None


@pytest.mark.parametrize("options, message", [
    ({"eval_every": 12, "rollout": 8}, "eval_every=12 must be a multiple of rollout=8"),
    ({"reward": "twins"}, "reward"),
    ({"log_std_init": 3.0}, "log_std_init"),
])
def test_bad_evaluation_options_are_refused_naming_the_field(options, message):
    with pytest.raises(ConfigError, match=message):
        AttackerTrainConfig(**options)


@pytest.mark.slow
def test_a_short_run_evaluates_on_schedule_and_reports_the_best_stealthy_checkpoint(tmp_path):
    pytest.importorskip("stable_baselines3")
    assert main(["--victims", "identity", "--out", str(tmp_path), "--timesteps", "16",
                 "--rollout", "8", "--steps", "4", "--cavs", "2", "--eval-episodes", "2",
                 "--eval-every", "8"]) == 0
    report = json.loads((tmp_path / "report.json").read_text())
    assert [row["timesteps"] for row in report["evaluations"]] == [0, 8, 16]
    assert report["learned"] == report["evaluations"][-1] and report["reward"] == "twin"
    assert report["best_stealthy"]["detection_rate"] == 0.0  # identity never rejects
    assert report["best_stealthy"]["removed"] == max(r["removed"] for r in report["evaluations"])
    assert report["zero_action"]["removed"] == 0.0
    fresh = report["best_stealthy"]["fresh_seeds"]  # the chosen checkpoint on other seeds
    assert fresh["ap70_clean"] != report["zero_action"]["ap70_clean"]
    for name in ("curve.csv", "evaluations.csv", "curve.png", "best.zip", "attacker.zip"):
        assert (tmp_path / name).is_file()
    assert len((tmp_path / "evaluations.csv").read_text().splitlines()) == 4
