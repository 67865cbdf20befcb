"""``roco-env train-policy``: a tiny run end to end, determinism, resume, bad options.

Tiny budgets (a few PPO rollouts of 2-step episodes on one small scenario) keep each run
a few seconds; they test the machinery, not that the policy learns (docs/learning.md and
the shipped run's report show that).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

pytest.importorskip("stable_baselines3")

from roco_env.cli import main  # noqa: E402
from roco_env.observation_modes import DIAGNOSTICS  # noqa: E402
from roco_env.policies.learned import LearnedPolicy  # noqa: E402
from roco_env.schema import ConfigError  # noqa: E402
from roco_env.training.rl.config import build_config  # noqa: E402
from roco_env.training.rl.curriculum import condition_env, draw_condition  # noqa: E402
from roco_env.training.rl.ppo import greedy, train  # noqa: E402

TINY = {"scenarios": ["v2xset_like"], "observation_mode": "raw", "episode_steps": 2,
        "n_steps": 8, "batch_size": 4, "n_epochs": 1, "eval_every": 8,
        "total_timesteps": 16, "eval_noises": [1.0], "net_arch": [8]}
TINY_ARGS = ["--scenarios", "v2xset_like", "--observation-mode", "raw", "--episode-steps", "2",
             "--n-steps", "8", "--batch-size", "4", "--n-epochs", "1", "--eval-every", "8",
             "--eval-noises", "1.0", "--net-arch", "8"]


def run_cli(out, *extra):
    return main(["train-policy", f"--out={out}", "--quiet", *TINY_ARGS, *extra])


def checkpoint_tensors(out):
    return torch.load(out / "checkpoint" / "policy.pt", weights_only=True)


def assert_same_weights(a, b):
    first, second = checkpoint_tensors(a), checkpoint_tensors(b)
    assert first.keys() == second.keys()
    for key in first:
        assert torch.equal(first[key], second[key]), key


def test_a_tiny_run_writes_weights_report_and_command(tmp_path):
    assert run_cli(tmp_path, "--total-timesteps=16") == 0
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["command"].startswith(f"roco-env train-policy --out={tmp_path}")
    assert "--total-timesteps=16" in report["command"]
    assert [p["timesteps"] for p in report["curve"]] == [0, 8, 16]
    assert set(report["baselines"]) == {"identity", "no_fusion", "coalign", "roco",
                                        "roco_antialias", "oracle"}
    assert report["baselines"]["no_fusion"]["reward"] == 0.0  # gain over no fusion
    assert (tmp_path / "learning_curve.png").stat().st_size > 1000
    assert "| learned |" in (tmp_path / "report.md").read_text()
    policy = LearnedPolicy(str(tmp_path / "learned_select.pt"))
    assert policy.env_overrides["action.mode"] == "select"


def test_the_exported_policy_acts_as_the_sb3_policy(tmp_path):
    config = build_config(TINY)
    result = train(config, tmp_path, progress=False, log=lambda m: None)
    from roco_env.training.rl.policy_export import save_policy
    save_policy(tmp_path / "w.pt", result.model.policy, result.env, config, {})
    learned, sb3 = LearnedPolicy(str(tmp_path / "w.pt")), greedy(result.model, result.env)
    env = condition_env(config, draw_condition(config, 3))
    observation, info = env.reset(seed=5)
    actions = []
    for _ in range(2):
        actions.append(sb3(observation, info))
        np.testing.assert_array_equal(learned(observation, info), actions[-1])
        observation, _, _, _, info = env.step(actions[-1])


def test_the_same_command_gives_the_same_weights(tmp_path):
    assert run_cli(tmp_path / "a", "--total-timesteps=16") == 0
    assert run_cli(tmp_path / "b", "--total-timesteps=16") == 0
    assert_same_weights(tmp_path / "a", tmp_path / "b")
    assert (tmp_path / "a" / "learned_select.pt").read_bytes() != b""
    assert run_cli(tmp_path / "c", "--total-timesteps=16", "--seed=1") == 0
    with pytest.raises(AssertionError):  # the seed matters: the check can fail
        assert_same_weights(tmp_path / "a", tmp_path / "c")


def test_a_rerun_continues_from_the_checkpoint_exactly(tmp_path):
    assert run_cli(tmp_path / "straight", "--total-timesteps=24") == 0
    assert run_cli(tmp_path / "resumed", "--total-timesteps=8") == 0  # stopped after 8 steps
    assert run_cli(tmp_path / "resumed", "--total-timesteps=24") == 0  # continues to 24
    assert_same_weights(tmp_path / "straight", tmp_path / "resumed")
    straight, resumed = (json.loads((tmp_path / d / "report.json").read_text())
                         for d in ("straight", "resumed"))
    assert [(p["timesteps"], p["reward"]) for p in straight["curve"]] == \
        [(p["timesteps"], p["reward"]) for p in resumed["curve"]]


def test_a_checkpoint_of_other_options_is_refused(tmp_path, capsys):
    assert run_cli(tmp_path, "--total-timesteps=8") == 0
    assert run_cli(tmp_path, "--total-timesteps=16", "--learning-rate=0.01") == 2
    assert "learning_rate" in capsys.readouterr().err


@pytest.mark.parametrize("values, field", [
    ({"n_steps": 7}, "n_steps"),
    ({"scenarios": ["nowhere"]}, "scenarios"),
    ({"noise_low": 2.0, "noise_high": 1.0}, "noise_high"),
    ({"action_mode": "steer"}, "action_mode"),
    ({"gamma": 1.5}, "gamma"),
    ({"eval_every": 100}, "eval_every"),
    ({"noise_models": ["pink"]}, "noise_models"),
    ({"batch_size": 1000}, "batch_size"),
    ({"net_arch": [0]}, "net_arch"),
    ({"learning_rat": 0.1}, "learning_rat"),
    ({"observation_keys": ["boxes", "boxes"]}, "observation_keys"),
])
def test_bad_options_name_the_field(values, field):
    with pytest.raises(ConfigError, match=field):
        build_config({**TINY, **values})


def test_bad_options_on_the_command_line_exit_2(tmp_path, capsys):
    assert run_cli(tmp_path, "--total-timesteps=16", "--n-steps=3") == 2
    assert "n_steps" in capsys.readouterr().err
    assert not (tmp_path / "checkpoint").exists()


def test_conditions_are_a_function_of_seed_and_index():
    config = build_config(TINY)
    assert draw_condition(config, 4) == draw_condition(config, 4)
    assert draw_condition(config, 4) != draw_condition(config, 5)
    noises = [draw_condition(build_config({**TINY, "scenarios": ["parking_lot"]}), i)
              for i in range(50)]
    assert all(0.0 <= c.noise <= 2.0 and c.density <= 1.0 for c in noises)
    assert {c.noise_model for c in noises} == {"gaussian", "ar1"}


def test_observation_keys_choose_what_the_policy_reads(tmp_path):
    from roco_env.training.rl.curriculum import CurriculumEnv
    config = build_config({**TINY, "observation_mode": "aligned",
                           "observation_keys": ["diagnostics", "collab_mask"]})
    env = CurriculumEnv(config)
    assert [key for key, _ in env.keys] == ["collab_mask", "diagnostics"]  # space order
    assert env.observation_space.shape == (5 + 5 * len(DIAGNOSTICS),)
    with pytest.raises(ValueError, match=r"observation_keys names \['pose'\]"):
        CurriculumEnv(build_config({**config.__dict__, "observation_keys": ["pose"]}))
