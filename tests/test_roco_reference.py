"""RoCo's fast path against reference results recorded with the plain numpy implementation
(tests/data/roco_reference.json: 24 random benchmark scenes, 2-6 agents, 10-80 objects,
pose errors 0-1.5 m/deg, three parameter sets). Speed work must not change a result. They
were recorded while the matching rounds weighed each edge by its box's information alone,
``round_information="box"``, so they pin that rule; the default one ("difference") is the
Python loop's, exactly in its discrete outcomes and to rounding in its floats
(tests/test_roco_kernels.py)."""

import json
from pathlib import Path

import numpy as np
import pytest

from roco_env.policies.roco import roco_align
from roco_env.testing.constructed_scenes import benchmark_scene

CASES = json.loads((Path(__file__).parent / "data" / "roco_reference.json").read_text())


@pytest.mark.parametrize("case", CASES, ids=lambda c: f"seed{c['seed']}-{sorted(c['params'])}")
def test_roco_matches_the_reference_path(case):
    scene = benchmark_scene(
        np.random.default_rng(case["seed"]),
        case["agents"],
        case["objects"],
        error_m=case["error"],
        error_deg=case["error"],
    )
    result = roco_align(*scene.args(), round_information="box", **case["params"])
    np.testing.assert_allclose(result.corrected, np.array(case["corrected"]), rtol=0, atol=1e-9)
    assert result.applied.tolist() == case["applied"]
    assert result.matched_pairs.shape[0] == case["pairs"]
