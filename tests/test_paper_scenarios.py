"""The dataset-shaped scenarios hold the parameters docs/paper-scenarios.md documents."""

from __future__ import annotations

import numpy as np
import pytest

import roco_env
from roco_env.scenario import load_scenario

# name -> (cavs, rsus, comm range m, cav range m, x_range, y_range, ground truth per ego-frame)
DOCUMENTED = {
    "v2xset_like": (3, 1, 70.0, 70.0, [-140.8, 140.8], [-40.0, 40.0], (13, 26)),
    "dair_like": (1, 1, 100.0, 100.0, [-100.0, 100.0], [-40.0, 40.0], (10, 21)),
}


@pytest.mark.parametrize("name", sorted(DOCUMENTED))
def test_parameters_match_the_documentation(name):
    cavs, rsus, comm, cav_range, x_range, y_range, _ = DOCUMENTED[name]
    config = load_scenario(name)
    assert (config.agents.cavs, config.agents.rsus) == (cavs, rsus)
    assert config.agents.comm_range == comm and config.agents.cav_range == cav_range
    assert config.evaluation.x_range == x_range and config.evaluation.y_range == y_range
    assert config.noise.model == "gaussian"
    assert (config.noise.sigma_t, config.noise.sigma_r) == (0.2, 0.2)
    assert config.fusion.nms_iou == 0.15
    assert config.max_collaborators >= cavs + rsus - 1  # every other agent fits a slot


@pytest.mark.parametrize("name", sorted(DOCUMENTED))
def test_traffic_density_gives_the_documented_ground_truth_count(name):
    low, high = DOCUMENTED[name][-1]
    env = roco_env.parallel_env(name, max_cycles=4)
    counts = []
    for seed in (0, 1):
        env.reset(seed=seed)
        for _ in range(3):
            zero = {agent: np.zeros(env.action_space(agent).shape) for agent in env.agents}
            _, _, _, _, infos = env.step(zero)
            counts += [info["n_gt"] for info in infos.values()]
    assert low <= np.mean(counts) <= high
