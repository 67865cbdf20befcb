"""The settings of ``roco-env train-policy``: one dataclass, the single place for defaults,
allowed values and the command line's options (:data:`FLAGS`, generated from it).

Every field is declared with :func:`roco_env.schema.spec`; :func:`build_config` checks a
mapping of values (unknown keys, types, ranges, choices). The dataclass's ``__post_init__``
checks every field the same way (:func:`roco_env.schema.check_fields`, so a
``PolicyTrainConfig(...)`` built directly is checked too) and then the rules one field's
spec cannot state (list items, fields that go together), raising
:class:`roco_env.schema.ConfigError` naming the field.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from roco_env.flags import SpecFlags
from roco_env.policies.reject_untested import GAP_CLIP_M
from roco_env.policies.spec import check_aligner_spec
from roco_env.scenario import OBSERVATION_MODES, ActionConfig, list_scenarios
from roco_env.schema import ConfigError, build, check_fields, spec

ACTION_MODES = ("correction", "residual", "select", "gate")
NOISE_MODELS = ("gaussian", "laplace", "bias", "drift", "ar1", "localization")
REWARDS = ("ap70_gain", "ap50_gain", "ap70", "ap50")
GUARDS = ("none", "reject_untested", "keep_tested")
REWARD_OVER = ("none", "base", "rule")
WHERE = "train-policy"


@dataclass
class PolicyTrainConfig:
    """PPO on a curriculum of conditions (roco_env.training.rl; docs/learning.md)."""

    action_mode: str = spec("select", choices=ACTION_MODES, doc="the env's action.mode")
    observation_mode: str = spec("aligned", choices=OBSERVATION_MODES,
                                 doc="the env's observation.mode")
    observation_keys: list[str] = spec([], doc="the observation entries the policy reads, "
                                       "in the space's order (empty: all)")
    action_choices: list[str] = spec([], doc="action.choices of select mode: the aligners' "
                                     "policy specs a slot picks among, reject after them "
                                     "(empty: the scenario's, by default identity, coalign, "
                                     "roco, roco_antialias)")
    action_base: str = spec("roco_antialias", doc="action.base: the aligner of residual and "
                            "gate modes and of the aligned observation's diagnostics")
    scenarios: list[str] = spec(["urban_intersection", "parking_lot", "v2xset_like"],
                                doc="scenarios an episode is drawn from")
    noise_low: float = spec(0.0, low=0.0, high=20.0,
                            doc="noise level drawn uniformly in [noise_low, noise_high]: "
                            "sigma_t m = sigma_r deg")
    noise_high: float = spec(2.0, low=0.0, high=20.0, doc="see noise_low")
    density_low: float = spec(0.8, low=0.0, high=2.0, low_open=True,
                              doc="scenario density multiplied by a factor drawn in "
                              "[density_low, density_high] (parking_lot: fill ratio, capped at 1)")
    density_high: float = spec(1.0, low=0.0, high=2.0, low_open=True, doc="see density_low")
    noise_models: list[str] = spec(["gaussian", "ar1"], doc="noise models drawn per episode")
    max_collaborators: int = spec(5, low=1, high=32, doc="N, fixed across the curriculum")
    max_boxes: int = spec(64, low=1, high=1024, doc="K, fixed across the curriculum")
    episode_steps: int = spec(8, low=1, high=1000, doc="env steps per training episode")
    reward: str = spec("ap70_gain", choices=REWARDS, doc="the env's reward")
    guard: str = spec("none", choices=GUARDS, doc="reject_untested: the slots action_base "
                      "computed no statistic for are rejected by rule (in training, "
                      "evaluation and the exported policy), the network decides the others; "
                      "keep_tested: the slots action_base tested take its pose by rule, the "
                      "network decides the untested ones (any choice or reject) "
                      "(select mode, aligned observation, action_base one of the choices)")
    guard_prefer: str = spec("", doc="keep_tested only, two action_choices: the other "
                             "choice, whose pose a tested slot takes instead of "
                             "action_base's (within guard_prefer_within_m of it), so the "
                             "tested slots follow the rule reject_untested:tested=THIS,"
                             "tested_within_m=M; empty: action_base's")
    guard_prefer_within_m: float | None = spec(
        None, low=0.0, high=GAP_CLIP_M, high_open=True, doc="m, in [0, 20) (gap_m is "
        "clipped at 20 m): a tested slot takes guard_prefer's pose only where it lies within "
        "this distance of action_base's (None: always); needs guard_prefer")
    reward_over: str = spec("none", choices=REWARD_OVER, doc="base: each training step's "
                            "reward minus the reward of taking action_base's pose for every "
                            "slot (behind the guard) on the same frame, so only deviations "
                            "from it are paid; rule: minus the reward of the guard's rule "
                            "alone (its tested slots' choice, untested slots rejected), so a "
                            "step that agrees with the rule pays 0 (select mode; evaluation "
                            "keeps the plain reward)")
    total_timesteps: int = spec(9600, low=1, doc="PPO env steps in all")
    n_steps: int = spec(320, low=1, doc="env steps per PPO rollout (a multiple of "
                        "episode_steps, so a checkpoint falls between episodes)")
    batch_size: int = spec(64, low=2, doc="PPO minibatch size")
    n_epochs: int = spec(5, low=1, high=100, doc="PPO epochs per rollout")
    learning_rate: float = spec(3e-4, low=0.0, high=1.0, low_open=True, doc="Adam step size")
    gamma: float = spec(0.0, low=0.0, high=1.0,
                        doc="discount: 0 for i.i.d. noise (a contextual bandit)")
    gae_lambda: float = spec(0.95, low=0.0, high=1.0, doc="GAE lambda")
    ent_coef: float = spec(0.01, low=0.0, high=1.0, doc="entropy bonus")
    clip_range: float = spec(0.2, low=0.0, high=1.0, low_open=True, doc="PPO clip range")
    net_arch: list[int] = spec([64, 64], doc="hidden widths of the policy and value MLPs (tanh)")
    eval_every: int = spec(1920, low=1, doc="env steps between evaluations and checkpoints "
                           "(a multiple of n_steps)")
    eval_noises: list[float] = spec([0.4, 1.2, 2.0, 3.0], doc="noise levels of the "
                                    "held-out evaluation (every scenario, eval_seeds seeds "
                                    "each)")
    eval_seeds: int = spec(1, low=1, high=100, doc="held-out evaluation seeds per condition")
    seed: int = spec(0, low=0, high=2**31 - 1, doc="training seed (weights, conditions, "
                     "episodes)")
    threads: int = spec(1, low=1, high=64, doc="torch CPU threads")

    def __post_init__(self) -> None:
        check_fields(self, WHERE)
        _check_lists(self)
        _check_ties(self)


def build_config(values: dict[str, Any]) -> PolicyTrainConfig:
    """A checked :class:`PolicyTrainConfig` from ``values`` (missing keys keep defaults)."""
    return build(PolicyTrainConfig, values, WHERE)


def _check_lists(config: PolicyTrainConfig) -> None:
    known = list_scenarios()
    for name in config.scenarios:
        if name not in known:
            raise ConfigError(f"{WHERE}: scenarios: unknown scenario {name!r}; choose from "
                              f"{known}")
    if not config.scenarios:
        raise ConfigError(f"{WHERE}: scenarios must name at least one scenario")
    if not config.noise_models or any(m not in NOISE_MODELS for m in config.noise_models):
        raise ConfigError(f"{WHERE}: noise_models={config.noise_models!r}; each one of "
                          f"{list(NOISE_MODELS)}")
    if not config.net_arch or any(not isinstance(w, int) or isinstance(w, bool) or w < 1
                                  for w in config.net_arch):
        raise ConfigError(f"{WHERE}: net_arch={config.net_arch!r} must be positive integers")
    if any(not isinstance(key, str) for key in config.observation_keys) or \
            len(set(config.observation_keys)) != len(config.observation_keys):
        raise ConfigError(f"{WHERE}: observation_keys={config.observation_keys!r} must be "
                          "distinct entry names of the observation")
    if not config.eval_noises or any(not isinstance(s, int | float) or isinstance(s, bool)
                                     or not 0 <= s <= 20 for s in config.eval_noises):
        raise ConfigError(f"{WHERE}: eval_noises={config.eval_noises!r} must be numbers in "
                          "[0, 20]")


def select_choices(config: PolicyTrainConfig) -> list[str]:
    """The select mode's choices: ``action_choices``, or the scenario default's."""
    return list(config.action_choices) or list(ActionConfig().choices)


def _check_choices(config: PolicyTrainConfig) -> None:
    if not config.action_choices:
        return
    if config.action_mode != "select":
        raise ConfigError(f"{WHERE}: action_choices applies to action_mode='select' only; "
                          f"got action_mode={config.action_mode!r}")
    for text in config.action_choices:
        try:
            check_aligner_spec(WHERE, "each of action_choices", text)
        except ValueError as exc:
            raise ConfigError(str(exc)) from exc
    if len(set(config.action_choices)) != len(config.action_choices):
        raise ConfigError(f"{WHERE}: action_choices={config.action_choices!r} must be "
                          "distinct")


def _check_ties(config: PolicyTrainConfig) -> None:
    _check_choices(config)
    if config.noise_high < config.noise_low:
        raise ConfigError(f"{WHERE}: noise_high={config.noise_high} must be >= "
                          f"noise_low={config.noise_low}")
    if config.density_high < config.density_low:
        raise ConfigError(f"{WHERE}: density_high={config.density_high} must be >= "
                          f"density_low={config.density_low}")
    if config.n_steps % config.episode_steps:
        raise ConfigError(f"{WHERE}: n_steps={config.n_steps} must be a multiple of "
                          f"episode_steps={config.episode_steps}")
    if config.eval_every % config.n_steps:
        raise ConfigError(f"{WHERE}: eval_every={config.eval_every} must be a multiple of "
                          f"n_steps={config.n_steps}")
    if config.total_timesteps % config.n_steps:
        raise ConfigError(f"{WHERE}: total_timesteps={config.total_timesteps} must be a "
                          f"multiple of n_steps={config.n_steps}")
    choices = select_choices(config)
    if config.reward_over != "none" and (config.action_mode != "select" or
                                          config.action_base not in choices):
        raise ConfigError(f"{WHERE}: reward_over={config.reward_over!r} needs "
                          f"action_mode='select' and action_base one of action_choices "
                          f"{choices}")
    if config.guard != "none" and (
            config.action_mode != "select" or config.observation_mode != "aligned"
            or config.action_base not in choices
            or not {"choice_diagnostics", "collab_mask"} <= set(config.observation_keys
                                                               or ("choice_diagnostics",
                                                                   "collab_mask"))):
        raise ConfigError(f"{WHERE}: guard={config.guard!r} needs action_mode='select', "
                          "observation_mode='aligned', action_base one of action_choices "
                          f"{choices} and observation_keys holding "
                          "choice_diagnostics and collab_mask (or empty)")
    _check_prefer(config, choices)
    if config.reward_over == "rule" and config.guard == "none":
        raise ConfigError(f"{WHERE}: reward_over='rule' needs a guard (reject_untested or "
                          "keep_tested): the rule is the guard's")
    if config.batch_size > config.n_steps:
        raise ConfigError(f"{WHERE}: batch_size={config.batch_size} must be <= "
                          f"n_steps={config.n_steps}")


def _check_prefer(config: PolicyTrainConfig, choices: list[str]) -> None:
    if config.guard_prefer_within_m is not None and not config.guard_prefer:
        raise ConfigError(f"{WHERE}: guard_prefer_within_m="
                          f"{config.guard_prefer_within_m} needs guard_prefer")
    if not config.guard_prefer:
        return
    if config.guard != "keep_tested":
        raise ConfigError(f"{WHERE}: guard_prefer={config.guard_prefer!r} needs "
                          f"guard='keep_tested'; got guard={config.guard!r}")
    if len(choices) != 2:
        raise ConfigError(f"{WHERE}: guard_prefer needs exactly two action_choices "
                          f"(action_base={config.action_base!r} and the preferred one); got "
                          f"action_choices={choices}")
    allowed = [c for c in choices if c != config.action_base]
    if config.guard_prefer not in allowed:
        raise ConfigError(f"{WHERE}: guard_prefer={config.guard_prefer!r} must be the "
                          f"action_choices entry other than action_base="
                          f"{config.action_base!r}: one of {allowed}")


# The command line's options (roco-env train-policy), one per field.
FLAGS = SpecFlags(PolicyTrainConfig, WHERE)
