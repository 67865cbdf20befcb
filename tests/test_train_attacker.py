"""Training a learned attacker (roco_env.training.rl.attacker): the single-agent view of
attacker_0, its clean twins, the evaluation, the options and a short PPO run."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from roco_env.training.rl import attacker
from roco_env.training.rl.attacker import FLAGS, AttackerEnv, AttackerTrainConfig, evaluate, main
from roco_env.training.rl.curriculum import INPUT_CLIP


def make(victims: str = "roco") -> AttackerEnv:
    return AttackerEnv("urban_intersection", victims, {"ghosts": 1}, 0.4, 3, cavs=2, rsus=1)


def test_the_attackers_view_is_scaled_as_the_learned_policies_and_its_episodes_end():
    env = make()
    observation, _ = env.reset()
    assert observation.shape == env.observation_space.shape and env.observation_space.contains(
        observation)
    assert env.observation_space.high.max() == INPUT_CLIP
    names, sizes = zip(*((key, int(np.prod(shape))) for key, shape in env.keys), strict=True)
    start = sum(sizes[: names.index("collab_mask")])
    mask = observation[start:start + sizes[names.index("collab_mask")]]
    assert set(mask.tolist()) == {0.0, 1.0}  # a mask stays 0/1 (its bound is 1)
    done, steps = False, 0
    while not done:
        observation, reward, terminated, truncated, _ = env.step(env.action_space.sample())
        done, steps = terminated or truncated, steps + 1
        assert -1.0 <= reward <= 0.0
    assert steps == 3 and env.episodes == 1


def test_the_zero_action_removes_nothing_a_lie_removes_ap_and_each_twin_is_played_once(
        monkeypatch):
    played = []
    original = attacker.play_episode

    def counted(*args, **kwargs):
        played.append(kwargs["seed"])
        return original(*args, **kwargs)

    monkeypatch.setattr(attacker, "play_episode", counted)
    env = make("identity")
    zero = evaluate(env, lambda o: np.zeros(6, np.float32), [0])
    assert zero["ap70"] == zero["ap70_clean"] and zero["attack_success"] == 0.0
    lie = evaluate(env, lambda o: np.array([1, 1, 1, 0, 0, -1], np.float32), [0])
    assert lie["ap70"] < lie["ap70_clean"] == zero["ap70_clean"]  # a 3 m, 3 deg lie
    assert played == [0]


@pytest.mark.slow
def test_a_short_ppo_run_writes_its_curve_and_report(tmp_path):
    pytest.importorskip("stable_baselines3")
    assert main(["--victims", "identity", "--out", str(tmp_path), "--timesteps", "16",
                 "--rollout", "8", "--steps", "4", "--cavs", "2", "--eval-episodes", "1"]) == 0
    report = json.loads((tmp_path / "report.json").read_text())
    assert len(report["curve"]) == 2 and (tmp_path / "curve.png").is_file()
    assert report["zero_action"]["attack_success"] == 0.0
    assert report["command"].startswith(f"python -m roco_env.training.rl.attacker "
                                        f"--out={tmp_path} --victims=identity ")


def test_the_recorded_options_reproduce_the_run():
    options = AttackerTrainConfig(victims="defend:base=roco", steps=4, budget_m=2.5)
    parser = argparse.ArgumentParser()
    FLAGS.add_to(parser)
    assert FLAGS.parse(parser.parse_args(FLAGS.argv(options))) == options


@pytest.mark.parametrize("argv, message", [
    (["--victims", "nope"], "unknown policy"),
    (["--steps", "0"], "steps=0 is out of range"),
    (["--budget-m", "-1"], "attack.params.budget_m=-1.0 is out of range"),
])
def test_bad_options_are_refused_naming_the_field(argv, message, capsys):
    assert main(argv + ["--out", "unused"]) == 2
    assert message in capsys.readouterr().err


def test_options_built_directly_are_checked_as_the_command_line_checks_them():
    from roco_env.schema import ConfigError

    with pytest.raises(ConfigError, match="cavs=0 is out of range"):
        AttackerTrainConfig(cavs=0)
    with pytest.raises(ConfigError, match="attack.params.budget_m=-1.0 is out of range"):
        AttackerTrainConfig(budget_m=-1.0)
