"""Stage registries (roco_env.stages): every built-in stage loads, a scenario's choices
and parameter checks come from the registry, and a user's stage registered in code or
installed with an entry point is selected from a scenario by name."""

from __future__ import annotations

import dataclasses
import textwrap
from dataclasses import dataclass

import numpy as np
import pytest

import roco_env
from roco_env import stages
from roco_env.evaluation import make_reward
from roco_env.fusion import make_fusion
from roco_env.fusion.late import LateFusion
from roco_env.noise import GaussianNoise, make_pose_noise
from roco_env.scenario import ConfigError, load_scenario, scenario_from_dict
from roco_env.schema import spec
from roco_env.sensing.detector import (
    AgentDetections,
    Perception,
    make_detector,
    realistic_detector,
)
from roco_env.traffic import make_traffic_source


@pytest.mark.parametrize("kind", stages.KINDS)
def test_every_built_in_stage_loads(kind):
    for name in stages.available_stages(kind):
        entry = stages.stage(kind, name)
        assert callable(entry.load_factory()), (kind, name)
        params = entry.params_class()
        assert params is None or params is dict or dataclasses.is_dataclass(params), (kind, name)


def test_scenario_choices_are_the_registry_names():
    with pytest.raises(ConfigError) as info:
        scenario_from_dict({"detector": {"preset": "lidar9000"}})
    message = str(info.value)
    assert "detector.preset='lidar9000'" in message
    for name in stages.available_stages("detector"):
        assert repr(name) in message


def test_a_registered_detector_is_selected_by_name_and_its_params_checked(registered, tmp_path):
    @dataclass
    class Params:
        keep: float = spec(0.5, low=0.0, high=1.0, doc="share of boxes kept")

    class Halving:
        """The realistic detector's boxes, only the first ``keep`` share of each agent's."""

        axial_headings = False

        def __init__(self, params, region):
            self.keep, self.inner = Params(**params).keep, realistic_detector({})

        def perceive(self, state, visibility, rng):
            detections = self.inner.perceive(state, visibility, rng).detections
            return Perception([_first(d, int(len(d.scores) * self.keep)) for d in detections])

    registered("detector", "halving", Halving, Params)
    path = tmp_path / "mine.yaml"
    path.write_text("detector:\n  preset: halving\n  params: {keep: 0.25}\n")
    config = load_scenario(path)
    assert config.detector.params == {"keep": 0.25}
    env = roco_env.parallel_env(path, max_cycles=2)
    full = roco_env.parallel_env("urban_intersection", max_cycles=2)
    observations, _ = env.reset(seed=1)
    reference, _ = full.reset(seed=1)
    agent = env.agents[0]
    assert 0 < observations[agent]["box_mask"].sum() < reference[agent]["box_mask"].sum()
    path.write_text("detector:\n  preset: halving\n  params: {keep: 2.0}\n")
    with pytest.raises(ConfigError, match=r"mine.yaml: detector.params.keep=2.0 .*\[0.0, 1.0\]"):
        load_scenario(path)
    path.write_text("detector:\n  preset: halving\n  params: {sigma_xy: 0.1}\n")
    with pytest.raises(ConfigError, match="sigma_xy is a parameter of detector.preset "
                                            "'ideal' / 'realistic', not of 'halving'"):
        load_scenario(path)


def test_a_registered_fusion_noise_reward_and_traffic_run_in_the_env(registered):
    calls = {"fuse": 0}

    class CountingFusion(LateFusion):
        def fuse(self, frame, egos, kept, poses):
            calls["fuse"] += 1
            return super().fuse(frame, egos, kept, poses)

    class StillNoise(GaussianNoise):
        """No error at all, whatever the levels."""

        def _error(self, rng):
            return np.zeros(self.std.shape)

    def count_reward(config):
        class Count:
            needs_alone = False

            def __call__(self, evaluation, alone):
                return float(len(evaluation.pred_scores))

        return Count()

    def synthetic_again(config):
        return make_traffic_source(load_scenario("urban_intersection"))

    registered("fusion", "counting", CountingFusion)
    registered("noise", "still", StillNoise.from_config)
    registered("reward", "n_pred", count_reward)
    registered("traffic", "again", synthetic_again)
    env = roco_env.parallel_env("urban_intersection", max_cycles=2, fusion="counting",
                                noise_model="still", reward="n_pred",
                                **{"traffic.source": "again"})
    _, infos = env.reset(seed=0)
    agent = env.agents[0]
    _, rewards, _, _, step_infos = env.step({a: np.zeros(env.action_space(a).shape)
                                             for a in env.agents})
    assert calls["fuse"] == 1
    filled = infos[agent]["n_collaborators"]
    assert filled and np.allclose(step_infos[agent]["rpe_before"][:filled], 0.0)
    assert rewards[agent] == step_infos[agent]["n_pred"] > 0


def test_an_installed_package_entry_point_is_found(tmp_path, monkeypatch):
    package = tmp_path / "site"
    (package / "my_noise_pkg").mkdir(parents=True)
    (package / "my_noise_pkg" / "__init__.py").write_text(textwrap.dedent("""
        from dataclasses import dataclass

        from roco_env.noise import GaussianNoise
        from roco_env.schema import spec


        @dataclass
        class Params:
            factor: float = spec(2.0, low=0.0, doc="std multiplier")


        def make(config, agent_ids, dt):
            noise = GaussianNoise.from_config(config, agent_ids, dt)
            noise.std = noise.std * Params(**config.params).factor
            return noise


        make.PARAMS = Params
        """))
    info = package / "my_noise_pkg-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: my-noise-pkg\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("[roco_env.noise]\nscaled = my_noise_pkg:make\n")
    monkeypatch.syspath_prepend(str(package))
    assert "scaled" in stages.available_stages("noise")
    config = scenario_from_dict({"noise": {"model": "scaled", "params": {"factor": 3.0}}})
    noise = make_pose_noise(config.noise, ("cav_0",), 0.1)
    assert np.allclose(noise.std, [[0.6, 0.6, np.radians(0.6)]])
    with pytest.raises(ConfigError, match="noise.params.factor=-1.0 is out of range"):
        scenario_from_dict({"noise": {"model": "scaled", "params": {"factor": -1.0}}})


def test_built_in_names_and_bad_registrations_are_refused():
    with pytest.raises(ConfigError, match="built in"):
        roco_env.register_stage("fusion", "late", LateFusion)
    with pytest.raises(ConfigError, match="unknown stage kind 'comms'; allowed: traffic"):
        roco_env.register_stage("comms", "x", LateFusion)
    with pytest.raises(ConfigError, match="factory must be callable"):
        roco_env.register_stage("fusion", "x", 3)
    with pytest.raises(ConfigError, match="params must be a dataclass, dict or None"):
        roco_env.register_stage("fusion", "x", LateFusion, params=3)
    with pytest.raises(ConfigError, match="name must be an identifier"):
        roco_env.register_stage("fusion", "a b", LateFusion)


def test_a_stage_that_cannot_load_names_itself(registered):
    registered("fusion", "ghost", "no_such_module_here:Fusion")
    config = scenario_from_dict({"fusion": {"method": "ghost"}})
    with pytest.raises(ConfigError, match="fusion 'ghost': cannot load "
                                            "'no_such_module_here:Fusion'"):
        make_fusion(config, None)


def test_the_built_in_factories_build_what_the_scenario_names():
    config = load_scenario("urban_intersection", reward="ap50_gain", detector="ideal")
    assert make_reward(config.evaluation).needs_alone
    assert make_reward(config.evaluation).threshold == 0.5
    assert not make_detector(config.detector).params["noisy"]
    with pytest.raises(ValueError, match="frames= is only used with traffic.source='frames'"):
        make_traffic_source(config, frames=[])


def _first(detections: AgentDetections, n: int) -> AgentDetections:
    return AgentDetections(detections.boxes[:n], detections.uncertainty[:n],
                           detections.scores[:n], detections.object_ids[:n])
