"""Scenarios as users pass them: names, paths, plain mappings, configs; saved and loaded back."""

import pytest

import roco_env
from roco_env.scenario import (
    ConfigError,
    ScenarioConfig,
    load_scenario,
    save_scenario,
    scenario_from_dict,
    scenario_to_dict,
)

SMALL = {"agents": {"cavs": 2, "rsus": 1}, "traffic": {"density": 1.0}, "max_boxes": 16}


@pytest.mark.parametrize("make", [lambda: SMALL, lambda: scenario_from_dict(SMALL)],
                         ids=["dict", "ScenarioConfig"])
def test_parallel_env_accepts_a_mapping_or_a_config(make):
    env = roco_env.parallel_env(make(), max_cycles=1, sigma_t=0.3)
    assert env.possible_agents == ["cav_0", "cav_1", "rsu_0"]
    assert env.config.noise.sigma_t == 0.3 and env.config.max_boxes == 16
    env.reset(seed=0)


def test_a_bad_mapping_names_the_key():
    with pytest.raises(ConfigError, match=r"<dict>: unknown key 'agents.cars'"):
        roco_env.parallel_env({"agents": {"cars": 2}})


@pytest.mark.parametrize("scenario", [123, None, ["urban_intersection"]])
def test_a_scenario_of_the_wrong_type_says_what_is_accepted(scenario):
    with pytest.raises(ConfigError, match=r"scenario must be a name from "
                                            r"roco_env.list_scenarios\(\), a \.yaml path, a mapping"
                                            r" of its keys or a ScenarioConfig; got"):
        roco_env.parallel_env(scenario)
    with pytest.raises(ConfigError, match=r"scenario must be a name .* or a \.yaml path; got"):
        load_scenario(scenario)


def test_a_folder_is_not_a_scenario_file(tmp_path):
    with pytest.raises(ConfigError, match=r"is a folder, not a scenario \.yaml file"):
        load_scenario(tmp_path)


def test_the_helpers_name_what_they_need(tmp_path):
    with pytest.raises(ConfigError, match=r"a ScenarioConfig is needed \(load_scenario\(name\) "
                                            r"or scenario_from_dict\(mapping\)\); got dict"):
        save_scenario(SMALL, tmp_path / "mine.yaml")
    with pytest.raises(ConfigError, match="got str"):
        scenario_to_dict("urban_intersection")
    with pytest.raises(ConfigError, match=r"<dict>: a scenario mapping needs the YAML keys "
                                            r"\(traffic, agents, \.\.\.\); got str"):
        scenario_from_dict("urban_intersection")


def test_save_scenario_round_trips(tmp_path):
    config = load_scenario("parking_lot", sigma_t=0.7, **{"noise.params.rho": 0.5},
                           noise_model="ar1")
    path = save_scenario(config, tmp_path / "mine.yaml")
    assert load_scenario(path) == config
    assert scenario_from_dict(scenario_to_dict(config)) == config
    assert roco_env.parallel_env(str(path)).config == config


def test_save_scenario_wants_a_yaml_name(tmp_path):
    with pytest.raises(ConfigError, match=r"must end in \.yaml or \.yml"):
        save_scenario(ScenarioConfig(), tmp_path / "mine.txt")


def test_the_helpers_are_public():
    for name in ("load_scenario", "save_scenario", "scenario_from_dict", "scenario_to_dict",
                 "ScenarioConfig"):
        assert name in roco_env.__all__ and callable(getattr(roco_env, name))
