"""Scenario library: every YAML validates and builds its traffic; errors name file/key/allowed."""

import re

import numpy as np
import pytest

from roco_env.scenario import ConfigError, list_scenarios, load_scenario
from roco_env.traffic import make_traffic_source

REQUIRED = {"highway_dense", "urban_intersection", "parking_lot", "traffic_jam", "v2x_crossroad",
            "highway_env_merge", "opv2v_replay", "crowded_intersection"}
NEEDS_DATASET = {"opv2v", "dair"}


def test_library_has_required_scenarios():
    assert REQUIRED <= set(list_scenarios())


@pytest.mark.parametrize("name", list_scenarios())
def test_every_scenario_loads_and_builds(name):
    config = load_scenario(name)
    assert config.name == name
    assert config.description
    assert config.evaluation.x_range[0] < config.evaluation.x_range[1]
    if config.traffic.source in NEEDS_DATASET:
        assert config.traffic.path is None  # the user supplies it
        return
    source = make_traffic_source(config)
    if config.traffic.source == "highway_env":
        return  # reset is exercised by tests/test_traffic_highway_env.py (slow simulator)
    state = source.reset(np.random.default_rng(0))
    assert state.agent_ids[: config.agents.cavs] == tuple(
        f"cav_{i}" for i in range(config.agents.cavs))
    assert state.num_agents == config.agents.cavs + config.agents.rsus
    assert state.num_objects > 20


def test_named_scenarios_match_their_description():
    v2x = load_scenario("v2x_crossroad")
    assert (v2x.agents.cavs, v2x.agents.rsus) == (1, 1)
    assert v2x.evaluation.x_range == [-100.8, 100.8]
    urban = load_scenario("urban_intersection")
    assert urban.agents.rsus == 1 and urban.traffic.layout == "intersection"
    crowded = load_scenario("crowded_intersection")
    assert (crowded.agents.cavs, crowded.agents.rsus) == (4, 1)
    assert crowded.traffic.density > urban.traffic.density
    state = make_traffic_source(crowded).reset(np.random.default_rng(0))
    assert state.num_objects >= 200


def test_replay_without_path_is_a_clear_error():
    config = load_scenario("opv2v_replay")
    with pytest.raises(ValueError, match="traffic.path"):
        make_traffic_source(config)


def test_overrides_reach_traffic_fields():
    config = load_scenario("highway_dense", density=2.0, **{"traffic.speed_limit": 20.0})
    assert config.traffic.density == 2.0 and config.traffic.speed_limit == 20.0
    with pytest.raises(ConfigError, match="traffic.speed_limit"):
        load_scenario("highway_dense", **{"traffic.speed_limit": 500.0})


@pytest.mark.parametrize("overrides, fragment", [
    ({"cavs": 2, "agents.cavs": 3}, "'cavs' and 'agents.cavs' both set agents.cavs"),
    ({"agents.cavs": 3, "cavs": 2}, "'agents.cavs' and 'cavs' both set agents.cavs"),
    ({"detector.params.sigma_xy": 0.5, "detector.params": {"sigma_xy": 0.3}},
     "'detector.params.sigma_xy' and 'detector.params' both set detector.params"),
])
def test_two_overrides_of_one_field_are_refused(overrides, fragment):
    """Either would win silently depending on the order the keywords were written in."""
    with pytest.raises(ConfigError, match=re.escape(fragment) + "; give one"):
        load_scenario("urban_intersection", **overrides)


@pytest.mark.parametrize("scenario, overrides, fragment", [
    ("opv2v_replay", {"density": 2.0}, "traffic.source='opv2v'"),
    ("urban_intersection", {"traffic.source": "frames", "traffic.density": 2.0},
     "traffic.source='frames'"),
    ("highway_env_merge", {"density": 2.5}, "traffic.source='highway_env' with layout 'merge'"),
])
def test_a_density_the_traffic_does_not_read_is_refused(scenario, overrides, fragment):
    """A crowding sweep over it would report identical scenes under different densities."""
    with pytest.raises(ConfigError, match=re.escape(f"override: traffic.density has no effect "
                                                      f"with {fragment}")):
        load_scenario(scenario, **overrides)


@pytest.mark.parametrize("scenario", ["opv2v_replay", "highway_env_merge"])
def test_a_scenes_own_density_is_no_change_and_is_taken(scenario):
    """A sweep may pass every scene its density: the scene's own value changes nothing."""
    own = load_scenario(scenario)
    assert load_scenario(scenario, density=own.traffic.density) == own


def test_a_density_the_traffic_reads_is_taken():
    assert load_scenario("highway_env_merge", density=2.0,
                         **{"traffic.layout": "highway"}).traffic.density == 2.0
    assert load_scenario("parking_lot", density=0.5).traffic.density == 0.5


@pytest.mark.parametrize(
    "text, fragments",
    [
        ("traffic:\n  lanez: 3\n", ["traffic.lanez", "traffic.lanes", "allowed"]),
        ("traffic:\n  density: many\n", ["traffic.density", "a number", "many"]),
        ("traffic:\n  density: -1\n", ["traffic.density", "out of range", "[0.0, 100.0]"]),
        ("traffic:\n  layout: spaghetti\n", ["traffic.layout", "spaghetti", "parking_lot"]),
        ("agents:\n  cavs: 99\n", ["agents.cavs", "out of range"]),
        ("traffic:\n  layout: merge\n", ["traffic.layout='merge'", "synthetic", "parking_lot"]),
        ("traffic: [1, 2\n", ["malformed YAML"]),
        ("agents:\n  cavs: 3\nagents:\n  rsus: 2\n",
         ["malformed YAML", "duplicate key 'agents' (first on line 1)", "line 3"]),
        ("agents:\n  cavs: 3\n  cavs: 5\n", ["duplicate key 'cavs' (first on line 2)"]),
        ("noise:\n  params: {rho: 0.5}\n",
         ["unknown key 'noise.params.rho'; allowed: none",
          "noise.params.rho is a parameter of noise.model 'ar1', not of 'gaussian'"]),
        ("noise:\n  model: bias\n  params: {rho: 0.5}\n",
         ["noise.params.rho is a parameter of noise.model 'ar1'", "not of 'bias'"]),
        ("noise:\n  params: {zzz: 1}\n", ["unknown key 'noise.params.zzz'; allowed: none"]),
        ("noise:\n  model: ar1\n  params: {rh0: 0.5}\n", ["noise.params.rh0", "allowed: "
                                                             "noise.params.rho"]),
        ("detector:\n  params: {weights: my.pt}\n",
         ["unknown key 'detector.params.weights'; allowed: detector.params.noisy",
          "detector.params.sigma_xy",
          "detector.params.weights is a parameter of detector.preset 'learned', not of "
          "'realistic'"]),
    ],
)
def test_validation_errors_name_file_key_and_allowed(tmp_path, text, fragments):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_scenario(path)
    message = str(info.value)
    assert str(path) in message
    for fragment in fragments:
        assert fragment in message


def test_yaml_merge_keys_still_load():
    from roco_env.schema import load_yaml

    assert load_yaml("base: &b {x: 1, y: 2}\nm:\n  <<: *b\n  x: 3\n")["m"] == {"x": 3, "y": 2}


def test_yaml_is_loaded_safely(tmp_path):
    path = tmp_path / "evil.yaml"
    path.write_text("name: !!python/object/apply:os.system ['echo hacked']\n")
    with pytest.raises(ConfigError, match="malformed YAML"):
        load_scenario(path)
