"""Input that used to be accepted or misread: each now works or names the field and the rule."""

import numpy as np
import pytest

import roco_env
from roco_env.cli import main
from roco_env.noise import make_pose_noise
from roco_env.scenario import (
    LAYOUTS,
    SOURCE_LAYOUTS,
    ConfigError,
    load_scenario,
    scenario_from_dict,
)
from roco_env.sensing.detector import PRESETS
from roco_env.stages import available_stages


def test_numpy_scalars_are_accepted():
    env = roco_env.parallel_env(cavs=np.int64(2), rsus=np.int32(0), sigma_t=np.float32(0.4),
                                features=np.bool_(False), max_cycles=1)
    cfg = env.config
    assert (cfg.agents.cavs, cfg.noise.sigma_t, cfg.features.enabled) == (2, 0.4000000059604645,
                                                                           False)
    assert type(cfg.agents.cavs) is int and type(cfg.features.enabled) is bool
    ranged = roco_env.parallel_env(**{"evaluation.x_range": [np.float32(-50), np.int64(50)]})
    assert ranged.config.evaluation.x_range == [-50.0, 50.0]


def test_yaml_exponent_is_a_number(tmp_path):
    path = tmp_path / "dense.yaml"
    path.write_text("traffic:\n  density: 1e1\n  min_gap: 2.5e0\n")
    cfg = load_scenario(path)
    assert cfg.traffic.density == 10.0 and cfg.traffic.min_gap == 2.5


def test_empty_yaml_is_an_error(tmp_path):
    path = tmp_path / "empty.yaml"
    path.write_text("# nothing yet\n")
    with pytest.raises(ConfigError, match="empty.yaml: the file is empty"):
        load_scenario(path)


def test_a_scene_needs_an_agent():
    with pytest.raises(ValueError, match=r"agents.cavs \+ agents.rsus must be >= 1"):
        roco_env.parallel_env(cavs=0, rsus=0)


def test_parking_density_is_a_fill_ratio():
    with pytest.raises(ConfigError, match=r"density=1.5.*parking_lot.*allowed \[0, 1\]"):
        load_scenario("parking_lot", density=1.5)
    assert load_scenario("parking_lot", density=0.9).traffic.density == 0.9


@pytest.mark.parametrize("bad", [[40.0, -40.0], [1.0], [0.0, 0.0], ["a", 3]])
def test_reversed_or_malformed_evaluation_range_fails_at_construction(bad):
    with pytest.raises(ConfigError, match=r"evaluation.y_range must be \[low, high\]"):
        roco_env.parallel_env(**{"evaluation.y_range": bad})


@pytest.mark.parametrize("action, fragment", [
    (np.zeros((5, 3), dtype=complex), "complex128"),
    (np.zeros((5, 3), dtype=bool), "bool"),
])
def test_complex_and_bool_actions_are_rejected(action, fragment):
    env = roco_env.parallel_env(cavs=2, rsus=0, max_cycles=2)
    env.reset(seed=0)
    actions = {a: np.zeros((5, 3)) for a in env.agents}
    actions["cav_1"] = action
    with pytest.raises(ValueError, match=f"'cav_1' must be an array of real numbers.*{fragment}"):
        env.step(actions)


@pytest.mark.parametrize("key, value, fragment", [
    ("rho", 1.0, r"noise.params.rho=1.0 is out of range; allowed \[0.0, 1.0\)"),
    ("rho", "high", "noise.params.rho expects a number"),
    ("gain", 1.0, "unknown key 'noise.params.gain'"),
])
def test_bad_noise_params_fail_when_the_yaml_loads(tmp_path, key, value, fragment):
    path = tmp_path / "ar1.yaml"
    path.write_text(f"noise:\n  model: ar1\n  params:\n    {key}: {value}\n")
    with pytest.raises(ConfigError, match=fragment):
        load_scenario(path)


def test_bad_detector_params_fail_when_the_yaml_loads(tmp_path):
    path = tmp_path / "det.yaml"
    path.write_text("detector:\n  params:\n    p_max: 1.5\n")
    with pytest.raises(ConfigError, match=r"det.yaml: detector.params.p_max=1.5 .*\[0.0, 1.0\]"):
        load_scenario(path)


def test_one_schema_serves_the_scenario_and_the_components():
    # every preset is a valid DetectorParams; every noise model's defaults build a model
    for preset in PRESETS.values():
        scenario_from_dict({"detector": {"params": preset}})
    for model in available_stages("noise"):
        cfg = scenario_from_dict({"noise": {"model": model}})
        make_pose_noise(cfg.noise, ("cav_0", "cav_1"), 0.1)
    with pytest.raises(ConfigError, match="unknown key 'traffic.params.lanes_count'; allowed: none"):
        scenario_from_dict({"traffic": {"params": {"lanes_count": 2}}})
    with pytest.raises(ConfigError, match="agents.cavs must be >= 1 with traffic.source"):
        scenario_from_dict({"traffic": {"source": "highway_env", "layout": "merge"},
                            "agents": {"cavs": 0, "rsus": 1}})


def test_the_layout_lists_are_written_once():
    from roco_env.traffic.generate import SYNTHETIC_LAYOUTS
    from roco_env.traffic.highway_env_source import ENV_IDS

    assert SYNTHETIC_LAYOUTS == SOURCE_LAYOUTS["synthetic"]
    assert tuple(ENV_IDS) == SOURCE_LAYOUTS["highway_env"]
    assert set(LAYOUTS) == set(SOURCE_LAYOUTS["synthetic"]) | set(SOURCE_LAYOUTS["highway_env"])


def test_cli_output_path_under_a_file_is_a_clean_error(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    code = main(["compare", "--policies", "identity", "--noise", "0", "--seeds", "1",
                 "--steps", "1", "--workers", "1", "--quiet", "--no-plots",
                 "--set", "cavs=2", "--set", "rsus=0", "--out", str(blocker / "out")])
    assert code == 2
    err = capsys.readouterr().err
    assert "roco-env compare: error:" in err and str(blocker) in err
    assert "Traceback" not in err


def test_cli_policy_parameter_type(capsys):
    code = main(["compare", "--policies", "roco:tau2=abc", "--quiet"])
    assert code == 2
    assert "tau2 expects a number; got 'abc'" in capsys.readouterr().err
