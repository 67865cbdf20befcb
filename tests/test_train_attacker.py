"""Training a learned attacker (roco_env.training.rl.attacker): the single-agent view of
attacker_0, its clean twin, the evaluation, and a short PPO run."""

from __future__ import annotations

import json

import numpy as np
import pytest

from roco_env.training.rl.attacker import AttackerEnv, evaluate, main


def make(victims: str = "roco"):
    def build(clean: bool = False) -> AttackerEnv:
        return AttackerEnv("urban_intersection", victims, {"ghosts": 1}, 0.4, 3, clean=clean,
                           cavs=2, rsus=1)
    return build


def test_the_attackers_view_is_flat_and_bounded_and_its_episodes_end():
    env = make()()
    observation, _ = env.reset()
    assert observation.shape == env.observation_space.shape and env.observation_space.contains(
        observation)
    done, steps = False, 0
    while not done:
        observation, reward, terminated, truncated, _ = env.step(env.action_space.sample())
        done, steps = terminated or truncated, steps + 1
        assert -1.0 <= reward <= 0.0
    assert steps == 3 and env.episodes == 1


def test_the_zero_action_removes_nothing_and_a_lie_removes_ap():
    zero = evaluate(make(), lambda o: np.zeros(6, np.float32), [0])
    assert zero["ap70"] == zero["ap70_clean"] and zero["attack_success"] == 0.0
    lie = evaluate(make("identity"), lambda o: np.array([1, 1, 1, 0, 0, -1], np.float32), [0])
    assert lie["ap70"] < lie["ap70_clean"]  # a 3 m, 3 deg lie identity cannot correct


@pytest.mark.slow
def test_a_short_ppo_run_writes_its_curve_and_report(tmp_path):
    pytest.importorskip("stable_baselines3")
    assert main(["--victims", "identity", "--out", str(tmp_path), "--timesteps", "16",
                 "--rollout", "8", "--steps", "4", "--cavs", "2", "--eval-episodes", "1"]) == 0
    report = json.loads((tmp_path / "report.json").read_text())
    assert len(report["curve"]) == 2 and (tmp_path / "curve.png").is_file()
    assert report["zero_action"]["attack_success"] == 0.0


def test_bad_options_are_refused(capsys):
    assert main(["--victims", "nope", "--out", "unused"]) == 2
    assert "unknown policy" in capsys.readouterr().err
