"""The prior-free aligners and roco_fallback against reference results recorded with the
plain numpy implementation (tests/data/prior_free_reference.json: benchmark scenes with
2-6 agents, 10-80 objects and pose errors 0-10 m/deg, plus jittered parking rows, for
every method and a few parameter sets). Speed work must not change a result: poses to
1e-9, the applied flags, the matched pairs and the iteration counts exactly."""

import json
from pathlib import Path

import numpy as np
import pytest

from roco_env.policies.base import AlignmentResult
from roco_env.policies.fallback import roco_fallback_align
from roco_env.policies.freealign import freealign_align
from roco_env.policies.ransac import ransac_align
from roco_env.policies.v2i_calib import v2i_calib_align
from roco_env.testing.constructed_scenes import (
    AlignmentScene,
    benchmark_scene,
    make_scene,
    parking_rows,
    pose_error,
)

REFERENCE = Path(__file__).parent / "data" / "prior_free_reference.json"

# The RoCo passes of roco_fallback as recorded: the matching rounds weighing each edge by
# its box's information alone (the default now weighs box minus landmark; the rounds are
# checked against the Python loop in tests/test_roco_kernels.py).
RECORDED_ROCO = {"round_information": "box"}

# roco_fallback without the second RoCo pass for slots RoCo itself moved far (the
# behaviour before refine_beyond_m / refine_beyond_deg existed)
UNREFINED = {**RECORDED_ROCO, "refine_beyond_m": None, "refine_beyond_deg": None}

# label -> (aligner, params)
CONFIGS = {
    "ransac": (ransac_align, {}),
    "ransac_all_pairs": (ransac_align, {"pair_neighbors": None, "score_boxes": None,
                                        "use_yaw_invariants": False}),
    "v2i_calib": (v2i_calib_align, {}),
    "v2i_calib_oiou_hungarian": (v2i_calib_align, {"metric": "oiou",
                                                   "association": "hungarian"}),
    "freealign": (freealign_align, {}),
    "freealign_distances_only": (freealign_align, {"edge_yaw_tolerance_deg": None,
                                                   "max_subgraph": None}),
    "ransac_raw": (ransac_align, {"do_no_harm": False}),
    "roco_fallback_unrefined": (roco_fallback_align, UNREFINED),
    "roco_fallback_v2i_calib": (roco_fallback_align, {**UNREFINED, "fallback": "v2i_calib"}),
    "roco_fallback_freealign": (roco_fallback_align, {**UNREFINED, "fallback": "freealign"}),
    "roco_fallback": (roco_fallback_align, RECORDED_ROCO),
}

# ("bench", seed, agents, objects, error m/deg) or ("parking", seed, translation m)
SCENES = [
    ["bench", 0, 2, 10, 0.0],
    ["bench", 1, 3, 20, 0.8],
    ["bench", 2, 5, 60, 0.8],
    ["bench", 3, 5, 60, 2.0],
    ["bench", 4, 5, 60, 5.0],
    ["bench", 5, 4, 40, 10.0],
    ["bench", 6, 6, 80, 3.0],
    ["bench", 7, 2, 30, 5.0],
    ["bench", 8, 3, 15, 1.5],
    ["parking", 0, 2.5],
    ["parking", 1, 5.0],
]


def build_scene(spec: list) -> AlignmentScene:
    """The constructed scene a SCENES entry names."""
    if spec[0] == "bench":
        _, seed, agents, objects, error = spec
        return benchmark_scene(np.random.default_rng(seed), agents, objects, error, error)
    _, seed, translation = spec
    rng = np.random.default_rng(seed)
    park = parking_rows(2, 14, origin=(-16, -3), occupancy=rng.random(28) < 0.85,
                        jitter=(0.05, 0.1, 2.0), rng=rng)
    agents = np.array([[-5.0, -12.0, 0.2], [6.0, 14.0, -2.5]])
    return make_scene(park, agents, [pose_error(translation, 0.5, 0.0)])


def run_case(label: str, scene: AlignmentScene) -> AlignmentResult:
    """One configuration on one scene."""
    align, params = CONFIGS[label]
    return align(*scene.args(), **params)


CASES = json.loads(REFERENCE.read_text())


@pytest.mark.parametrize("case", CASES, ids=lambda c: f"{c['config']}-{c['scene']}")
def test_prior_free_matches_the_reference_path(case):
    result = run_case(case["config"], build_scene(case["scene"]))
    np.testing.assert_allclose(result.corrected, np.array(case["corrected"]), rtol=0, atol=1e-9)
    assert result.applied.tolist() == case["applied"]
    assert result.matched_pairs.tolist() == case["matched_pairs"]
    assert (result.outer_iterations, result.solver_iterations) == (case["outer"], case["solver"])


def test_reference_covers_applied_and_kept_slots():
    """The reference must exercise both outcomes of every do-no-harm method, or it pins
    nothing."""
    for label, (_, params) in CONFIGS.items():
        applied = [flag for c in CASES if c["config"] == label for flag in c["applied"]]
        assert any(applied), label
        assert not all(applied) or not params.get("do_no_harm", True), label
