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
    from roco_env.policies.constructed_scenes import (
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
