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
from roco_env.policies.reject_untested import STATISTIC  # noqa: E402
from roco_env.schema import ConfigError  # noqa: E402
from roco_env.training.rl.config import build_config  # noqa: E402
from roco_env.training.rl.curriculum import (  # noqa: E402
    condition_env,
    draw_condition,
    env_overrides,
    eval_conditions,
)
from roco_env.training.rl.ppo import build_model, greedy, train  # noqa: E402

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


def test_every_baseline_gets_a_line_in_the_learning_curve(tmp_path):
    """More baselines than colours (a guarded run has 7, here 9): each is a dashed line
    with its name in the legend, none dropped; replot() redraws a saved report's PNG."""
    from roco_env.training.rl.policy_report import COLOURS, PLOT, replot

    names = [f"baseline_{k}" for k in range(len(COLOURS) + 2)]
    curve = [{"timesteps": 0, "wall_s": 0.0, "reward": 0.1, "ap70": 0.3},
             {"timesteps": 8, "wall_s": 2.0, "reward": 0.2, "ap70": 0.4}]
    report = {"config": {"action_mode": "select"}, "command": "roco-env train-policy",
              "weights": "w.pt", "sha256": "0", "curve": curve, "final": curve[-1],
              "baselines": {name: {"reward": k / 10, "ap70": 0.5}
                            for k, name in enumerate(names)}}
    (tmp_path / "report.json").write_text(json.dumps(report))
    axes = replot(tmp_path).axes[0]
    dashed = [line for line in axes.get_lines() if line.get_linestyle() == "--"]
    assert [line.get_label() for line in dashed] == names
    assert [line.get_ydata()[0] for line in dashed] == [k / 10 for k in range(len(names))]
    legend = [text.get_text() for text in axes.get_legend().get_texts()]
    assert legend == ["learned (select)", *names]
    assert (tmp_path / PLOT).stat().st_size > 1000
    assert "| baseline_8 | 0.8000 | 0.5000 |" in (tmp_path / "report.md").read_text()


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


def test_the_training_env_sets_the_choices_the_exported_file_records():
    """In select mode the training env sets action.choices even without --action-choices
    (the defaults), so a scenario's own choices never train what the file calls others."""
    from roco_env.training.rl.policy_export import policy_env_overrides
    config = build_config(TINY)
    env = condition_env(config, draw_condition(config, 0))
    assert env_overrides(config)["action.choices"] == \
        policy_env_overrides(config)["action.choices"] == \
        list(env.env.config.action.choices) == ["identity", "coalign", "roco", "roco_antialias"]
    env.close()


def test_a_checkpoint_saved_before_a_config_field_existed_resumes(tmp_path):
    """A field the saved config lacks (action_choices, added later) compares as its
    default: adding a field never blocks a resume with the same options."""
    assert run_cli(tmp_path, "--total-timesteps=8") == 0
    path = tmp_path / "checkpoint" / "state.json"
    state = json.loads(path.read_text())
    del state["config"]["action_choices"]
    path.write_text(json.dumps(state))
    assert run_cli(tmp_path, "--total-timesteps=16") == 0
    report = json.loads((tmp_path / "report.json").read_text())
    assert [p["timesteps"] for p in report["curve"]] == [0, 8, 16]


GUARDED_KEYS = {"observation_mode": "aligned",
                "observation_keys": ["choice_diagnostics", "collab_mask"], "noise_low": 3.0,
                "noise_high": 3.0}
GUARDED = {**TINY, **GUARDED_KEYS, "guard": "reject_untested"}
KEEP_TESTED = {**GUARDED, "guard": "keep_tested",
               "action_choices": ["roco_antialias", "roco_fallback"]}
RULE_C = "reject_untested:tested=roco_fallback,tested_within_m=0.5"  # hand rule C
PREFER = {**KEEP_TESTED, "guard_prefer": "roco_fallback", "guard_prefer_within_m": 0.5}


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
    ({"guard": "always"}, "guard"),
    ({"guard": "reject_untested"}, "guard"),  # TINY's raw observation has no diagnostics
    ({"guard": "reject_untested", "observation_mode": "aligned",
      "observation_keys": ["diagnostics", "collab_mask"]}, "guard"),
    ({"reward_over": "base", "action_mode": "gate"}, "reward_over"),
    ({"reward_over": "base", "action_base": "oracle"}, "reward_over"),
    ({"action_choices": ["roco", "nonesuch"]}, "action_choices"),
    ({"action_choices": ["roco", "roco"]}, "action_choices"),
    ({"action_choices": [1]}, "action_choices must be .* aligner.*got 1"),
    ({"action_choices": ["roco", "defend"]}, "action_choices .*action.mode 'gate'"),
    ({"action_choices": ["roco", "reject_untested"]}, "action_choices .*action.mode 'select'"),
    ({"action_choices": ["learned_select"]}, "action_choices .*action.mode 'select'"),
    ({"action_choices": ["roco"], "action_mode": "gate"}, "action_choices"),
    ({**GUARDED_KEYS, "guard": "keep_tested",
      "action_choices": ["roco", "roco_fallback"]}, "action_choices"),  # base not a choice
    ({**PREFER, "guard": "reject_untested"}, "guard_prefer"),
    ({**PREFER, "guard_prefer": "roco_antialias"}, "guard_prefer"),  # action_base itself
    ({**PREFER, "guard_prefer": "roco"}, "guard_prefer"),  # not a choice
    ({**PREFER, "action_choices": ["roco_antialias", "roco_fallback", "roco"]},
     "guard_prefer"),  # gap_m is to the nearest other choice: two choices only
    ({**PREFER, "guard_prefer": ""}, "guard_prefer_within_m=0.5 needs guard_prefer"),
    ({**PREFER, "guard_prefer_within_m": 20.0}, "guard_prefer_within_m"),
    ({**PREFER, "guard_prefer_within_m": -0.1}, "guard_prefer_within_m"),
    ({**GUARDED, "guard": "none", "reward_over": "rule"}, "reward_over"),
])
def test_bad_options_name_the_field(values, field):
    with pytest.raises(ConfigError, match=field):
        build_config({**TINY, **values})


@pytest.mark.parametrize("values, message, unsaid", [
    ({"guard": "reject_untested"}, "guard_prefer='roco_fallback' needs guard='keep_tested'; "
     "got guard='reject_untested'$", "action_choices"),
    ({"guard_prefer": "roco_antialias"}, "guard_prefer='roco_antialias' must be the "
     r"action_choices entry other than action_base='roco_antialias': one of "
     r"\['roco_fallback'\]$", "keep_tested"),
    ({"guard_prefer": "roco"}, r"guard_prefer='roco' must be .*one of \['roco_fallback'\]$",
     "keep_tested"),
    ({"action_choices": ["roco_antialias", "roco_fallback", "roco"]},
     r"guard_prefer needs exactly two action_choices .*got action_choices="
     r"\['roco_antialias', 'roco_fallback', 'roco'\]$", "keep_tested"),
])
def test_a_bad_guard_prefer_names_the_one_condition_it_fails(values, message, unsaid):
    """The guard_prefer error says which condition failed (the guard, the number of
    choices, or which choice) with its allowed values, not the list of all of them."""
    with pytest.raises(ConfigError, match=message) as error:
        build_config({**PREFER, **values})
    assert unsaid not in str(error.value)


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


def test_the_guard_rejects_the_untested_slots_in_training_and_in_the_exported_policy(tmp_path):
    """v2xset_like at 3 m / 3 deg: the training env rejects exactly the slots
    roco_antialias left untested whatever the action, and the exported file acts behind
    the same rule (its guard) as the greedy SB3 policy does."""
    from roco_env.policies.learned import Guard
    from roco_env.training.rl.curriculum import CurriculumEnv
    from roco_env.training.rl.policy_export import save_policy

    config = build_config(GUARDED)
    env = CurriculumEnv(config)
    untested = 0
    for _, filled, blind, info in guarded_steps(env, 3, 0):  # identity everywhere
        np.testing.assert_array_equal(info["rejected"][filled], blind[filled])
        untested += int(blind.sum())
    assert untested >= 1
    model = build_model(config, env)  # untrained: the export, not the learning, is tested
    save_policy(tmp_path / "w.pt", model.policy, env, config, {})
    learned, sb3 = LearnedPolicy(str(tmp_path / "w.pt")), greedy(model, env)
    assert learned.guard == Guard(3, None, "network")
    play = condition_env(config, draw_condition(config, 3))
    observation, info = play.reset(seed=1)
    np.testing.assert_array_equal(learned(observation, info), sb3(observation, info))


def guarded_steps(env, base, choice):
    """(action played behind the guard, filled, untested by choice ``base``, info) of two
    steps of ``env`` (reset with seed 1) where the network samples ``choice`` everywhere."""
    from roco_env.training.rl.curriculum import guarded_action

    env.reset(seed=1)
    rows = []
    for _ in range(2):
        observation = env._observation
        filled = observation["collab_mask"] > 0
        blind = filled & (observation["choice_diagnostics"][:, base, STATISTIC] == -1)
        sampled = np.full(len(filled), choice, np.int64)
        played = guarded_action(env.guard, sampled, observation)
        rows.append((played, filled, blind, env.step(sampled)[4]))
    return rows


def test_reward_over_the_base_pays_only_what_a_deviation_changes():
    """With reward_over=base a step that takes roco_antialias's pose (behind the guard)
    pays exactly 0, and a deviating step its reward minus that of the base's action on
    the same frame (the env played twice from the same state)."""
    from roco_env.training.rl.curriculum import CurriculumEnv

    over, plain = (CurriculumEnv(build_config({**GUARDED, "reward_over": value}))
                   for value in ("base", "none"))
    for env in (over, plain):
        env.reset(seed=1)
    keep = np.full(5, 3)
    assert over.step(keep)[1] == 0.0
    plain.step(keep)
    deviate = np.zeros(5, np.int64)  # identity: differs from roco_antialias at 3 m
    paid = over.step(deviate)[1]
    gained = plain.step(deviate)[1]
    twin = CurriculumEnv(build_config(GUARDED))
    twin.reset(seed=1)
    twin.step(keep)
    assert paid == pytest.approx(gained - twin.step(keep)[1], abs=1e-12)
    assert paid != 0.0


def test_a_guarded_run_is_compared_with_its_rule_alone():
    """A network behind the guard is compared with the rule it acts behind: the
    ``reject_untested`` baseline plays roco_antialias's choice for every slot with the
    untested slots rejected, in the training env (an unguarded run has no such row)."""
    from roco_env.training.rl.evaluate import RULE, baselines_of, evaluate_baseline

    guarded = build_config({**GUARDED, "eval_noises": [5.0], "eval_seeds": 3})
    assert baselines_of(guarded)[-1] == RULE and RULE not in baselines_of(build_config(TINY))
    rewards, rejected = [], 0
    for condition in eval_conditions(guarded):
        env = condition_env(guarded, condition)
        observation, _ = env.reset(seed=condition.seed)
        for _ in range(guarded.episode_steps):
            filled = observation["collab_mask"] > 0
            blind = filled & (observation["choice_diagnostics"][:, 3, STATISTIC] == -1)
            observation, reward, _, _, info = env.step(np.where(blind, 4, 3))
            np.testing.assert_array_equal(info["rejected"][filled], blind[filled])
            rewards.append(reward)
            rejected += int(blind.sum())
        env.close()
    assert rejected >= 1  # the rule had something to reject
    assert evaluate_baseline(guarded, RULE)["reward"] == pytest.approx(np.mean(rewards),
                                                                       abs=1e-12)


def test_keep_tested_takes_the_base_on_tested_slots_and_lets_the_network_choose_elsewhere(
        tmp_path):
    """--action-choices roco_antialias roco_fallback --guard keep_tested, v2xset_like at
    3 m / 3 deg: whatever the sampled action, every slot roco_antialias tested takes it
    (0) and the untested ones take the action (here reject: the env rejects exactly them); the
    exported file records the choices and its guard, and acts as the greedy SB3 policy."""
    from roco_env.policies import make_policy
    from roco_env.policies.learned import Guard
    from roco_env.training.rl.curriculum import CurriculumEnv
    from roco_env.training.rl.policy_export import save_policy

    config = build_config(KEEP_TESTED)
    env = CurriculumEnv(config)
    untested = 0
    reject = len(config.action_choices)
    for played, filled, blind, info in guarded_steps(env, 0, reject):  # reject everywhere
        np.testing.assert_array_equal(played[filled], np.where(blind, reject, 0)[filled])
        # what the env applied: without the guard every filled slot would be rejected
        np.testing.assert_array_equal(info["rejected"][filled], blind[filled])
        untested += int(blind.sum())
    assert untested >= 1
    model = build_model(config, env)
    save_policy(tmp_path / "w.pt", model.policy, env, config, {})
    learned = make_policy("learned_select", weights=str(tmp_path / "w.pt"))
    assert learned.guard == Guard(0, None, "keep", "network")
    assert learned.env_overrides["action.choices"] == ["roco_antialias", "roco_fallback"]
    sb3 = greedy(model, env)
    play = condition_env(config, draw_condition(config, 3))
    observation, info = play.reset(seed=1)
    np.testing.assert_array_equal(learned(observation, info), sb3(observation, info))


def test_a_file_for_other_choices_is_refused_naming_them(tmp_path):
    """A file trained over [roco_antialias, roco_fallback] run in an env with the default
    four choices: the error names action.choices and the file's choices."""
    from roco_env.training.rl.curriculum import CurriculumEnv
    from roco_env.training.rl.policy_export import save_policy

    config = build_config(KEEP_TESTED)
    env = CurriculumEnv(config)
    save_policy(tmp_path / "w.pt", build_model(config, env).policy, env, config, {})
    learned = LearnedPolicy(str(tmp_path / "w.pt"))
    other = condition_env(build_config(GUARDED), draw_condition(config, 0))
    observation, info = other.reset(seed=1)
    with pytest.raises(ValueError, match=r"choice_diagnostics.*action\.choices="
                                         r"\['roco_antialias', 'roco_fallback'\]"):
        learned(observation, info)


def test_action_choices_on_the_command_line(tmp_path, capsys):
    assert run_cli(tmp_path, "--total-timesteps=8", "--action-choices", "roco",
                   "nonesuch") == 2
    assert "action_choices" in capsys.readouterr().err


def rule_c_episode():
    """(config, env, observation, info) of parking_lot at 3 m / 3 deg, env seed 1, in the
    PREFER run's modes: in two steps rule C keeps roco_antialias on 3 tested slots (an
    alias: roco_fallback's pose more than 0.5 m away), takes roco_fallback on 4 and
    rejects 1 untested slot."""
    from roco_env.training.rl.curriculum import Condition

    config = build_config(PREFER)
    env = condition_env(config, Condition("parking_lot", 3.0, None, "gaussian", 1))
    return (config, env, *env.reset(seed=1))


def test_the_prefer_guard_follows_rule_c_on_tested_slots_exactly():
    """--guard keep_tested --guard-prefer roco_fallback --guard-prefer-within-m 0.5: on a
    seeded episode the guard's rule alone equals the fixed policy C's action on every slot,
    and whatever the network samples (reject, roco_fallback, roco_antialias) the tested
    slots take C's choice and the untested ones the sample."""
    from roco_env.policies.spec import parse_policy_spec
    from roco_env.training.rl.curriculum import guarded_action, training_guard

    config, env, observation, info = rule_c_episode()
    guard, rule_c = training_guard(config), parse_policy_spec(RULE_C).build()
    kinds = set()
    for _ in range(2):
        expected = rule_c(observation, info)
        filled = observation["collab_mask"] > 0
        untested = filled & (observation["choice_diagnostics"][:, 0, STATISTIC] == -1)
        np.testing.assert_array_equal(
            guard.rule(2, observation["choice_diagnostics"], observation["collab_mask"]),
            expected)
        for sampled in range(3):
            played = guarded_action(guard, np.full(5, sampled), observation)
            np.testing.assert_array_equal(played[filled & ~untested],
                                          expected[filled & ~untested])
            np.testing.assert_array_equal(played[untested], sampled)
        kinds |= {int(a) for a in expected[filled]}
        observation, _, _, _, info = env.step(expected)
    assert kinds == {0, 1, 2}  # C kept roco_antialias, took roco_fallback and rejected


def test_a_prefer_guarded_file_records_its_guard_and_acts_as_the_sb3_policy(tmp_path):
    """The exported file's guard holds prefer / prefer_within_m; loaded, it acts as the
    greedy SB3 policy behind the same guard, and its tested slots as rule C."""
    from roco_env.policies import make_policy
    from roco_env.policies.learned import Guard
    from roco_env.policies.spec import parse_policy_spec
    from roco_env.training.rl.curriculum import CurriculumEnv
    from roco_env.training.rl.policy_export import save_policy

    config = build_config(PREFER)
    env = CurriculumEnv(config)
    model = build_model(config, env)
    save_policy(tmp_path / "w.pt", model.policy, env, config, {})
    learned = make_policy("learned_select", weights=str(tmp_path / "w.pt"))
    assert learned.guard == Guard(0, None, "keep", "network", 1, 0.5)
    assert learned.metadata["guard"] == {"keep": 0, "tested": "keep", "untested": "network",
                                         "prefer": 1, "prefer_within_m": 0.5}
    _, _, observation, info = rule_c_episode()
    action = learned(observation, info)
    np.testing.assert_array_equal(action, greedy(model, env)(observation, info))
    tested = (observation["collab_mask"] > 0) & \
        (observation["choice_diagnostics"][:, 0, STATISTIC] != -1)
    np.testing.assert_array_equal(action[tested],
                                  parse_policy_spec(RULE_C).build()(observation, info)[tested])


def test_the_rule_row_is_named_by_the_fixed_policy_it_plays():
    """The guard's rule alone is the row ``rule``, labelled with the reject_untested spec
    it plays: rule C behind the prefer guard, reject_untested's default otherwise."""
    from roco_env.training.rl.evaluate import RULE, rule_spec

    assert RULE == "rule"
    assert rule_spec(build_config(PREFER)) == RULE_C
    assert rule_spec(build_config(GUARDED)) == rule_spec(build_config(KEEP_TESTED)) == \
        "reject_untested"
    assert rule_spec(build_config({**PREFER, "guard_prefer_within_m": None})) == \
        "reject_untested:tested=roco_fallback"
    assert rule_spec(build_config({**GUARDED, "action_base": "roco"})) == \
        "reject_untested:base=roco"


def old_rule_key(baselines):
    """``baselines`` as written before the rule row was renamed ``rule``."""
    return {("reject_untested" if name == "rule" else name): score
            for name, score in baselines.items()}


def test_a_checkpoint_naming_the_rule_reject_untested_resumes_with_the_row_rule(tmp_path):
    """Checkpoints written before the rename call the rule row ``reject_untested``: a
    resumed run reads it as ``rule`` and report.md writes the spec it plays beside it."""
    guarded = ["--observation-mode=aligned", "--observation-keys", "choice_diagnostics",
               "collab_mask", "--guard=reject_untested"]
    assert run_cli(tmp_path, "--total-timesteps=8", *guarded) == 0
    path = tmp_path / "checkpoint" / "state.json"
    state = json.loads(path.read_text())
    state["baselines"] = old_rule_key(state["baselines"])
    path.write_text(json.dumps(state))
    assert run_cli(tmp_path, "--total-timesteps=16", *guarded) == 0
    report = json.loads((tmp_path / "report.json").read_text())
    assert list(report["baselines"]) == ["identity", "no_fusion", "coalign", "roco",
                                         "roco_antialias", "oracle", "rule"]
    assert f"| rule (`reject_untested`) | {report['baselines']['rule']['reward']:.4f} |" \
        in (tmp_path / "report.md").read_text()


def test_replot_of_an_old_report_labels_the_rule_row_with_rule_c(tmp_path):
    """replot() of a report.json whose rule row is ``reject_untested`` (written before the
    rename) writes it as ``rule`` with rule C's spec beside it, in report.md and the
    legend."""
    from dataclasses import asdict

    from roco_env.training.rl.policy_report import replot

    curve = [{"timesteps": 0, "wall_s": 0.0, "reward": 0.1, "ap70": 0.3}]
    report = {"config": asdict(build_config(PREFER)), "command": "roco-env train-policy",
              "weights": "w.pt", "sha256": "0", "curve": curve, "final": curve[0],
              "baselines": {"roco_antialias": {"reward": 0.2, "ap70": 0.4},
                            "reject_untested": {"reward": 0.25, "ap70": 0.45}}}
    (tmp_path / "report.json").write_text(json.dumps(report))
    legend = [text.get_text() for text in replot(tmp_path).axes[0].get_legend().get_texts()]
    assert legend == ["learned (select)", "roco_antialias", f"rule: {RULE_C}"]
    written = (tmp_path / "report.md").read_text()
    assert f"| rule (`{RULE_C}`) | 0.2500 | 0.4500 |" in written
    assert "reject_untested |" not in written


def test_reward_over_the_rule_pays_only_what_a_deviation_from_rule_c_changes():
    """reward_over=rule behind the prefer guard: a step that plays rule C's action pays
    exactly 0, one that keeps an untested slot (with roco_antialias's untested pose) its
    reward minus C's on the same frame; the run is compared with C (the rule alone) in its
    evaluation."""
    from roco_env.training.rl.curriculum import CurriculumEnv
    from roco_env.training.rl.evaluate import RULE, baselines_of

    assert baselines_of(build_config(PREFER))[-1] == RULE
    over, plain, twin = (CurriculumEnv(build_config({**PREFER, "reward_over": value}))
                         for value in ("rule", "none", "none"))
    for env in (over, plain, twin):
        env.reset(seed=1)
    paid, gained, reference = [], [], []
    for _ in range(2):
        observation = over._observation
        rule = over.guard.rule(2, observation["choice_diagnostics"], observation["collab_mask"])
        keep_all = np.zeros(5, np.int64)  # untested slots: roco_antialias, not reject
        paid.append(over.step(keep_all)[1])
        gained.append(plain.step(keep_all)[1])
        reference.append(twin.step(rule)[1])
        deviates = not np.array_equal(over.guard.constrain(keep_all, 2, observation[
            "choice_diagnostics"], observation["collab_mask"]), rule)
        assert paid[-1] == (pytest.approx(gained[-1] - reference[-1], abs=1e-12) if deviates
                            else 0.0)
    assert any(value != 0.0 for value in paid)  # a step deviated from C, and paid so
    rule_env = CurriculumEnv(build_config({**PREFER, "reward_over": "rule"}))
    rule_env.reset(seed=1)
    observation = rule_env._observation
    assert rule_env.step(rule_env.guard.rule(2, observation["choice_diagnostics"],
                                             observation["collab_mask"]))[1] == 0.0
