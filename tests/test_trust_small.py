"""Issue 27's smaller trust fixes: non-finite weights, stateful policies without ``info``,
scenario paths relative to their YAML, and the clearer errors of bad arguments."""

import re

import numpy as np
import pytest

from roco_env.sensing import BevGrid
from roco_env.sensing.lidar import ScanNoise

TINY_GRID = BevGrid((-25.6, 25.6), (-12.8, 12.8), 0.8)


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
@pytest.mark.parametrize("fusion", ["max", "gated"])
def test_weights_with_non_finite_values_are_an_error_naming_the_file(tmp_path, fusion, bad):
    """A NaN detector or fusion-gate weight would score every box NaN (no detection, every
    reward 0): the loader refuses the file, naming it and the tensor."""
    import torch

    from roco_env.sensing.learned import BevDetectorNet, NetConfig, save_checkpoint
    from roco_env.sensing.learned.model import load_checkpoint

    net = BevDetectorNet(NetConfig(widths=(4, 8, 8), fusion=fusion))
    name = [n for n in net.state_dict() if n.startswith("gate.")][0] if fusion == "gated" else (
        next(iter(net.state_dict())))
    with torch.no_grad():
        net.state_dict()[name].view(-1)[0] = bad
    path = tmp_path / "w.pt"
    save_checkpoint(path, net, TINY_GRID, ScanNoise(), {})
    with pytest.raises(ValueError, match=rf"file {re.escape(str(path))} holds non-finite .* in {name}"):
        load_checkpoint(path)


def _collab_observation(filled: int = 1) -> dict:
    mask = np.zeros(2, np.int8)
    mask[:filled] = 1
    return {"collab_mask": mask}


class _Constant:
    """An inner policy that corrects every slot by the same (1, 0, 0)."""

    last_result = None

    def __call__(self, observation, info=None):
        return np.tile(np.array([1.0, 0.0, 0.0], np.float32), (2, 1))


@pytest.mark.parametrize("info", [None, {"collaborators": ["cav_1"]}, {"agent": "cav_0"},
                                  {"agent": "cav_0", "collaborators": []}])
def test_temporal_smoothing_without_ids_refuses_instead_of_keying_by_slot(info):
    """Keyed by slot, one instance serving two egos mixed their filters (each ego's slot 0
    is another collaborator): without the ids it needs, it is an error saying what to pass."""
    from roco_env.policies.temporal import TemporalSmoothing

    wrapper = TemporalSmoothing(_Constant())
    with pytest.raises(ValueError, match=r"temporal smoothing.*(infos\[agent\]|slots \[0\])"):
        wrapper(_collab_observation(), info)


def test_one_temporal_instance_keeps_each_egos_filters_apart():
    from roco_env.policies.temporal import TemporalSmoothing

    wrapper = TemporalSmoothing(_Constant(), max_age=5)
    wrapper(_collab_observation(), {"agent": "cav_0", "collaborators": ["cav_1"]})
    assert set(wrapper._filters) == {("cav_0", "cav_1")}
    wrapper(_collab_observation(), {"agent": "cav_1", "collaborators": ["cav_0"]})
    assert set(wrapper._filters) == {("cav_0", "cav_1"), ("cav_1", "cav_0")}


def test_pooled_roco_without_ids_refuses_instead_of_keying_by_slot():
    from roco_env.policies import make_policy
    from roco_env.testing.constructed_scenes import (
        make_scene,
        pose_error,
        random_objects,
        to_observation,
    )

    objects = random_objects(np.random.default_rng(1), 12, 40.0)
    scene = make_scene(objects, np.array([[0.0, 0.0, 0.0], [15.0, 5.0, 0.5]]),
                       [pose_error(0.8, 0.8, 0.3)])
    observation = to_observation(scene, max_boxes=16, max_collaborators=2)
    policy = make_policy("roco", pooled_significance=0.9999)
    with pytest.raises(ValueError, match=r"roco with pooled_significance .*infos\[agent\]"):
        policy(observation)


def _write_scenario(folder, text: str):
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "mine.yaml"
    path.write_text(text, encoding="utf-8")
    return path


def test_relative_paths_in_a_scenario_file_are_relative_to_its_folder(tmp_path, monkeypatch):
    from roco_env.scenario import load_scenario

    path = _write_scenario(tmp_path / "scenes", "traffic:\n  path: ../data/opv2v\n"
                           "detector:\n  preset: learned\n  params:\n    weights: w.pt\n")
    monkeypatch.chdir(tmp_path.parent)  # the working directory is elsewhere
    config = load_scenario(path)
    folder = (tmp_path / "scenes").absolute()
    assert config.traffic.path == str(folder / ".." / "data" / "opv2v")
    assert config.detector.params["weights"] == str(folder / "w.pt")
    # Overrides (Python or command line) stay relative to the working directory.
    overridden = load_scenario(path, **{"traffic.path": "here", "detector.params":
                                        {"weights": "other.pt"}})
    assert overridden.traffic.path == "here" and overridden.detector.params["weights"] == "other.pt"
    absolute = _write_scenario(tmp_path / "abs", f"traffic:\n  path: {tmp_path / 'data'}\n")
    assert load_scenario(absolute).traffic.path == str(tmp_path / "data")


def test_a_scenario_file_that_is_not_utf8_is_an_error_naming_it(tmp_path):
    from roco_env.scenario import ConfigError, load_scenario

    path = tmp_path / "latin1.yaml"
    path.write_bytes("description: caf\u00e9\n".encode("latin-1"))
    with pytest.raises(ConfigError, match=rf"{re.escape(str(path))}: not UTF-8 text"):
        load_scenario(path)


@pytest.mark.parametrize("pair, message", [
    ([1e9, 0.0], r"noise.per_agent.cav_1\[0\] \(sigma_t\)=1000000000.0 is out of range; "
                 r"allowed \[0.0, 20.0\]"),
    ([0.5, 90], r"noise.per_agent.cav_1\[1\] \(sigma_r\)=90.0 is out of range; "
                r"allowed \[0.0, 45.0\]"),
    ([0.5], r"noise.per_agent.cav_1 must be \[sigma_t m, sigma_r deg\]"),
], ids=["sigma_t", "sigma_r", "pair"])
def test_per_agent_noise_has_the_global_caps(tmp_path, pair, message):
    from roco_env.scenario import ConfigError, load_scenario

    path = _write_scenario(tmp_path, f"noise:\n  per_agent:\n    cav_1: {pair}\n")
    with pytest.raises(ConfigError, match=rf"{re.escape(str(path))}: {message}"):
        load_scenario(path)
    with pytest.raises(ConfigError, match=rf"override: {message}"):
        load_scenario("urban_intersection", **{"noise.per_agent": {"cav_1": pair}})
    assert load_scenario("urban_intersection", **{"noise.per_agent": {"cav_1": [20, 45]}}
                         ).noise.per_agent == {"cav_1": [20.0, 45.0]}


@pytest.mark.parametrize("layout", ["highway", "roundabout"])
def test_the_no_vehicle_message_advises_a_density_that_places_vehicles(layout):
    from roco_env.scenario import load_scenario
    from roco_env.traffic.synthetic import make_synthetic

    def traffic(density):
        config = load_scenario("urban_intersection", cavs=0, **{"traffic.layout": layout,
                                                                "traffic.density": density})
        return make_synthetic(config).reset(np.random.default_rng(0))

    with pytest.raises(ValueError, match=r"use traffic.density >= ([0-9.]+)") as error:
        traffic(0.3)
    advised = float(re.search(r">= ([0-9.]+)", str(error.value)).group(1))
    assert 0.3 < advised < 1.0 and traffic(advised).num_objects >= 1


def test_bad_policy_names_and_frames_are_errors_naming_the_argument():
    from roco_env.policies import make_policy
    from roco_env.scenario import load_scenario
    from roco_env.traffic import make_traffic_source

    with pytest.raises(ValueError, match=r"make_policy: name must be a policy name .*got None"):
        make_policy(None)
    config = load_scenario("urban_intersection", cavs=1, **{"traffic.source": "frames"})
    frame = {"object_ids": [7], "object_boxes": [[0, 0, 0, 4, 2, 1.5, 0]], "cav_object_ids": [7]}
    with pytest.raises(ValueError, match=r"frames\[0\] must be a roco_env.traffic.frames.Frame"
                                         r" .*got dict"):
        make_traffic_source(config, frames=[frame])


def test_the_pettingzoo_floor_has_the_registry_roco_env_uses():
    """roco_env registers its env ids with ``pettingzoo.register`` and checks
    ``pettingzoo.parallel_registry``, which PettingZoo has from 1.27 on."""
    from pathlib import Path

    from packaging.requirements import Requirement

    root = Path(__file__).resolve().parents[1]
    assert "pettingzoo.parallel_registry" in (root / "roco_env" / "registration.py").read_text()
    # The one quoted requirement naming pettingzoo (tomllib is Python 3.11+).
    (line,) = re.findall(r'"(pettingzoo[^"]*)"', (root / "pyproject.toml").read_text())
    pettingzoo = Requirement(line)
    assert "1.27.0" in pettingzoo.specifier
    assert not any(old in pettingzoo.specifier for old in ("1.24.0", "1.25.0", "1.26.1"))


def test_gymnasium_make_of_the_ego_env_does_not_warn():
    import warnings

    import gymnasium

    import roco_env
    from roco_env.wrappers import EgoEnv

    assert "rgb_array" in EgoEnv.metadata["render_modes"]  # on the class, where make reads it
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        env = gymnasium.make(roco_env.EGO_ENV_ID, render_mode="rgb_array")
    env.close()
