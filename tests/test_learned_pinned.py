"""The learned pipeline's outputs pinned to recorded results (tests/data/learned_pinned.json;
first recorded before the pipeline's speed work, re-recorded when the rasters gained the
point-offset channels, with the numpy rasteriser checked bit-identical to the compiled one): LiDAR scans and rasters, encoder maps, own and
intermediate-fused decoded boxes with labels, of seeded steps. Speed work must not
change a result: scans, rasters and own detections match to rounding of the sums;
fused boxes to 1e-5 (fusion's compiled warp differs from grid_sample by rounding,
docs/perception.md, section 4).

The network gets weights drawn from a numpy generator (not the shipped ones, which
are retrained independently), so the record pins the pipeline, not a training run.
Large arrays are pinned by fingerprints (shape, sum and a sum weighted by a fixed
random vector: any changed cell moves the weighted sum); boxes are pinned in full.
Regenerate (only for a deliberate, documented change of results) with
``python tests/test_learned_pinned.py``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from roco_env.fusion.intermediate import intermediate_fusion
from roco_env.scenario import load_scenario
from roco_env.sensing import BevGrid, compute_visibility
from roco_env.sensing.learned import BevDetectorNet, LearnedDetector, NetConfig, save_checkpoint
from roco_env.sensing.lidar import LIDAR_CHANNELS, ScanNoise, lidar_rasters, sample_scans
from roco_env.traffic import make_traffic_source

RECORD = Path(__file__).parent / "data" / "learned_pinned.json"
GRID = BevGrid((-70.4, 70.4), (-40.0, 40.0), 0.8)
# (scenario, traffic seed, scan seed): a crossing with an RSU and a dense highway.
CASES = (("urban_intersection", 3, 7), ("highway_dense", 5, 11))
EVAL_RANGE = ((-140.8, 140.8), (-40.0, 40.0))
HEAT_BIAS = -1.0
HEAD_SCALE = 0.3


def _fingerprint(array: np.ndarray) -> list:
    flat = np.asarray(array, dtype=float).ravel()
    weights = np.random.default_rng(0).random(flat.size)
    return [list(np.shape(array)), float(flat.sum()), float(flat @ weights)]


def _rounded(array: np.ndarray) -> list:
    """Nested lists of floats to 9 significant digits (compared at rtol 1e-5)."""
    return np.vectorize(lambda v: float(f"{v:.9g}"), otypes=[float])(
        np.asarray(array, dtype=float)).tolist()


def _seeded_weights(path: Path) -> Path:
    """A weights file of a (24, 48, 32) network with numpy-drawn weights (torch-independent)."""
    net = BevDetectorNet(NetConfig(len(LIDAR_CHANNELS), (24, 48, 32)))
    rng = np.random.default_rng(2024)
    state = net.state_dict()
    for name, value in state.items():
        if name.endswith("running_var"):
            drawn = 0.5 + rng.random(value.shape)
        elif value.is_floating_point():
            fan_in = max(1, value[0].numel()) if value.dim() > 1 else 1
            drawn = rng.standard_normal(value.shape) / np.sqrt(fan_in)
        else:
            continue
        state[name] = torch.as_tensor(drawn, dtype=value.dtype)
    # Heatmap logits around sigmoid(-1) = 0.27 (some peaks above the 0.2 threshold), car-sized
    # boxes (log length, width, height) with small head weights, so NMS has neighbours to suppress.
    state["heads.weight"] *= HEAD_SCALE
    state["heads.bias"][0] = HEAT_BIAS
    state["heads.bias"][3:6] = torch.log(torch.tensor([6.0, 2.5, 1.6]))
    net.load_state_dict(state)
    save_checkpoint(path, net, GRID, ScanNoise(), {"purpose": "pinned test"})
    return path


def _outputs(weights: Path) -> dict:
    detector = LearnedDetector(weights)
    out = {}
    for name, traffic_seed, scan_seed in CASES:
        state = make_traffic_source(load_scenario(name)).reset(np.random.default_rng(traffic_seed))
        visibility = compute_visibility(state)
        scans = sample_scans(state, visibility, ScanNoise(), np.random.default_rng(scan_seed))
        rasters = lidar_rasters(scans, visibility.ray_ranges, GRID)
        detections, features = detector.perceive(state, visibility,
                                                 np.random.default_rng(scan_seed))
        n = state.num_agents
        egos = list(range(n))
        collaborators = [[j for j in range(n) if j != i][:3] for i in egos]
        poses_rng = np.random.default_rng(scan_seed)
        poses = [np.asarray([state.agent_poses[j] - state.agent_poses[i] for j in c])
                 + poses_rng.normal(0.0, [0.5, 0.5, 0.05], (len(c), 3))
                 for i, c in zip(egos, collaborators, strict=True)]
        fused = intermediate_fusion(detector, features, state, egos, collaborators, poses,
                                    *EVAL_RANGE)
        out[name] = {
            "scans": [[_fingerprint(s.x), _fingerprint(s.y), _fingerprint(s.z),
                       _fingerprint(s.obj)] for s in scans],
            "rasters": [_fingerprint(r) for r in rasters],
            "features": _fingerprint(features.maps.numpy()),
            "boxes": [_rounded(d.boxes) for d in detections],
            "scores": [_rounded(d.scores) for d in detections],
            "uncertainty": [_rounded(d.uncertainty) for d in detections],
            "object_ids": [d.object_ids.tolist() for d in detections],
            "fused_boxes": [_rounded(f.boxes) for f in fused],
            "fused_scores": [_rounded(f.scores) for f in fused],
        }
    return out


@pytest.fixture(scope="module")
def outputs(tmp_path_factory):
    threads = torch.get_num_threads()
    try:
        return _outputs(_seeded_weights(tmp_path_factory.mktemp("pinned") / "net.pt"))
    finally:
        torch.set_num_threads(threads)


def _assert_same_fingerprints(got: list, want: list, rtol: float, what: str) -> None:
    assert len(got) == len(want), what
    for g, w in zip(got, want, strict=True):
        assert g[0] == w[0], f"{what}: shape {g[0]} != {w[0]}"
        np.testing.assert_allclose(g[1:], w[1:], rtol=rtol, atol=1e-9, err_msg=what)


@pytest.mark.parametrize("case", [c[0] for c in CASES])
def test_scans_and_rasters_match_the_record(outputs, case):
    got, want = outputs[case], json.loads(RECORD.read_text())[case]
    assert len(got["scans"]) == len(want["scans"])
    for a, (g, w) in enumerate(zip(got["scans"], want["scans"], strict=True)):
        _assert_same_fingerprints(g, w, 1e-12, f"scan of agent {a}")
    _assert_same_fingerprints(got["rasters"], want["rasters"], 1e-12, "rasters")


@pytest.mark.parametrize("case", [c[0] for c in CASES])
def test_detections_and_fused_boxes_match_the_record(outputs, case):
    got, want = outputs[case], json.loads(RECORD.read_text())[case]
    _assert_same_fingerprints([got["features"]], [want["features"]], 1e-5, "encoder maps")
    assert got["object_ids"] == want["object_ids"]
    assert sum(len(b) for b in want["boxes"]) > 20 and sum(len(b) for b in want["fused_boxes"]) > 20
    for key in ("boxes", "scores", "uncertainty", "fused_boxes", "fused_scores"):
        assert [len(b) for b in got[key]] == [len(b) for b in want[key]], key
        for g, w in zip(got[key], want[key], strict=True):
            np.testing.assert_allclose(np.array(g), np.array(w), rtol=1e-5, atol=1e-5,
                                       err_msg=key)


if __name__ == "__main__":
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        record = _outputs(_seeded_weights(Path(tmp) / "net.pt"))
    RECORD.write_text(json.dumps(record, indent=None) + "\n")
    print(f"wrote {RECORD}")
