"""The settings dataclasses of the commands check themselves as they are constructed
(roco_env.schema.check_fields): built directly or by roco_env.schema.build, a bad value gets
the same message; values come out as build gives them; a stress run declares each shared
setting once and reads each policy spec once."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from roco_env.schema import ConfigError, build, check_fields, optional_type, spec
from roco_env.stress import study
from roco_env.stress.space import load_space
from roco_env.stress.study import SearchOptions, SearchSettings, StressOptions
from roco_env.training.detector_config import TrainConfig
from roco_env.training.rl.config import PolicyTrainConfig

BAD = [
    (TrainConfig, {"lr": 0.0}, r"train-detector: lr=0.0 is out of range; allowed (0.0, inf)"),
    (TrainConfig, {"fusion": "min"},
     "train-detector: fusion='min' is not allowed; choose one of ['max', 'gated']"),
    (TrainConfig, {"steps": "3"}, "train-detector: steps expects an integer; got '3' (str)"),
    (TrainConfig, {"init": 5}, "train-detector: init expects a string; got 5 (int)"),
    (PolicyTrainConfig, {"gamma": 2.0},
     "train-policy: gamma=2.0 is out of range; allowed [0.0, 1.0]"),
    (PolicyTrainConfig, {"reward": "ap90"}, "train-policy: reward='ap90' is not allowed"),
    (StressOptions, {"budget": 0}, "stress: budget=0 is out of range; allowed [1, inf)"),
    (StressOptions, {"sampler": "grid"}, "stress: sampler='grid' is not allowed"),
    (StressOptions, {"gif": "yes"}, "stress: gif expects true or false; got 'yes' (str)"),
]


@pytest.mark.parametrize("cls, values, message", BAD, ids=[f"{c.__name__}-{next(iter(v))}"
                                                           for c, v, _ in BAD])
def test_direct_construction_and_build_refuse_a_bad_value_alike(cls, values, message):
    with pytest.raises(ConfigError) as direct:
        cls(**values)
    with pytest.raises(ConfigError) as built:
        build(cls, values, message.partition(":")[0])
    assert str(direct.value) == str(built.value)
    assert str(direct.value).startswith(message)


def test_a_search_refuses_a_bad_value_as_constructed():
    space = load_space()
    with pytest.raises(ConfigError, match=r"stress: steps=0 is out of range; allowed \[1, inf\)"):
        SearchSettings(out="o", policy="roco", space=space, steps=0)
    with pytest.raises(ConfigError, match="stress: space expects a SearchSpace; got 'x'"):
        SearchSettings(out="o", policy="roco", space="x")
    with pytest.raises(ValueError, match="unknown policy 'rocco'"):
        SearchSettings(out="o", policy="rocco", space=space)
    with pytest.raises(ValueError, match="seed must be None or an integer >= 0; got -1"):
        SearchSettings(out="o", policy="roco", space=space, seeds=(0, -1))
    with pytest.raises(ConfigError, match="stress: --address needs --backend ray"):
        StressOptions(policy=["roco"], out="o", address="auto")


def test_direct_construction_gives_the_values_build_gives():
    direct = TrainConfig(lr=1, seed=np.int64(3), scenarios=["parking_lot"])
    assert direct == build(TrainConfig, {"lr": 1, "seed": np.int64(3),
                                         "scenarios": ["parking_lot"]}, "train-detector")
    assert type(direct.lr) is float and type(direct.seed) is int
    assert direct.scenarios == ("parking_lot",)
    assert PolicyTrainConfig(net_arch=(32,)).net_arch == [32]


@dataclasses.dataclass(frozen=True)
class Inner:
    depth: int = spec(2, low=0)


@dataclasses.dataclass(frozen=True)
class Outer:
    rate: float | None = spec(0.5, low=0.0, high=1.0)
    inner: Inner = dataclasses.field(default_factory=Inner)

    def __post_init__(self) -> None:
        check_fields(self, "outer")


def test_check_fields_checks_a_frozen_dataclass_of_any_kind():
    assert Outer(rate=None).rate is None and type(Outer(rate=1).rate) is float
    with pytest.raises(ConfigError, match=r"outer: rate=2.0 is out of range; allowed \[0.0, 1.0\]"):
        Outer(rate=2.0)
    with pytest.raises(ConfigError, match="outer: inner expects a Inner; got {}"):
        Outer(inner={})


def test_optional_type_strips_none_once_for_the_schema_and_the_flags():
    assert optional_type(int | None) == (int, True)
    assert optional_type(tuple[float, float] | None) == (tuple[float, float], True)
    assert optional_type(list[str]) == (list[str], False)


def test_the_shared_settings_are_declared_once_and_each_policy_spec_read_once(monkeypatch):
    shared = {f.name for f in dataclasses.fields(SearchOptions)}
    own = {"policy", "space", "gif"}
    assert {f.name for f in dataclasses.fields(StressOptions)} == shared | own
    assert {f.name for f in dataclasses.fields(SearchSettings)} == shared | {"policy", "space"}
    read = []

    def counting(text):
        read.append(text)
        return parse(text)

    parse = study.parse_policy_spec
    monkeypatch.setattr(study, "parse_policy_spec", counting)
    options = StressOptions(policy=["roco:tau2=2,lam=1", "coalign", "roco:lam=1,tau2=2"],
                            out="o", budget=3, seeds=[1, 2], sampler="tpe")
    searches = options.searches(load_space())
    assert [s.policy for s in searches] == ["roco:lam=1,tau2=2", "coalign"]
    assert read == options.policy  # once per policy given
    assert all(s.budget == 3 and s.seeds == (1, 2) and s.out == "o" for s in searches)
