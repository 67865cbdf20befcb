"""The learned BEV detector: network shapes, decoding, shipped weights, fusion, training, errors."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch
from conftest import tiny_detector_start

import roco_env
from roco_env.fusion.intermediate import fuse_maps, fuse_on_canvas, fusion_canvas
from roco_env.geometry import transform_boxes
from roco_env.metrics import APAccumulator
from roco_env.policies import available_policies, make_policy
from roco_env.policies.spec import merge_env_overrides
from roco_env.scenario import ConfigError
from roco_env.sensing import BevGrid, warp_bev
from roco_env.sensing.learned import (
    BevDetectorNet,
    LearnedDetector,
    NetConfig,
    load_checkpoint,
    make_learned_detector,
    save_checkpoint,
    sha256_of,
    shipped_weights_path,
)
from roco_env.sensing.learned.network import HEAD_CHANNELS
from roco_env.sensing.learned.targets import _max_3x3, build_targets, decode, feature_grid
from roco_env.sensing.lidar import LIDAR_CHANNELS, ScanNoise
from roco_env.training.data import VALIDATION_SEED_BASE, make_scenes

# sha256 of the shipped weights (roco_env/sensing/learned/weights/: the detector alone, "max",
# and gated/: the same detector with its fusion gate, the default), each the output of the
# training command recorded in the report.md beside it.
SHIPPED_SHA256 = {"max": "a1b7291bbbee908a173234878330e6bce96a7334ed582876f6c80bb237506a85",
                  "gated": "64b711d271a0679c447f3fe19e1d0c55bb0476479feb65917dd71fa86eb4615f"}

GRID = BevGrid((-70.4, 70.4), (-40.0, 40.0), 0.8)
FGRID = feature_grid(GRID, 2)


@pytest.fixture(scope="module")
def detector():
    return LearnedDetector()


@pytest.fixture(scope="module")
def scene():
    return make_scenes(("urban_intersection",), 1, VALIDATION_SEED_BASE + 99, GRID, ScanNoise())[0]


def test_forward_shapes():
    net = BevDetectorNet(NetConfig(widths=(8, 16, 12))).eval()
    raster = torch.rand(3, len(LIDAR_CHANNELS), GRID.H, GRID.W)
    features = net.encode(raster)
    assert features.shape == (3, 12, GRID.H // 2, GRID.W // 2) and torch.all(features >= 0)
    maps = net.decode(features)
    assert {k: v.shape[1] for k, v in maps.items()} == HEAD_CHANNELS
    assert all(v.shape[-2:] == (FGRID.H, FGRID.W) for v in maps.values())
    with pytest.raises(ValueError, match="raster must have shape"):
        net.encode(torch.rand(1, 3, GRID.H, GRID.W))


def test_inference_network_folds_batch_norm_without_changing_outputs(detector):
    net = load_checkpoint(shipped_weights_path())
    trained = BevDetectorNet(net.net)
    trained.load_state_dict(net.state_dict)
    trained.eval()
    raster = torch.rand(2, len(LIDAR_CHANNELS), GRID.H, GRID.W)
    with torch.no_grad():
        expected = trained(raster)
        got = detector.net(raster.to(memory_format=torch.channels_last))
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in detector.net.modules())
    assert any(isinstance(m, torch.nn.BatchNorm2d) for m in trained.modules())
    for name, value in expected.items():
        torch.testing.assert_close(got[name], value, rtol=1e-4, atol=1e-4)


def test_parameter_budget(detector):
    assert sum(p.numel() for p in detector.net.parameters()) <= 1_000_000


def _perfect_maps(boxes: np.ndarray) -> dict[str, torch.Tensor]:
    """Head maps that say exactly ``boxes`` (one per feature cell)."""
    t = build_targets([boxes], FGRID)
    maps = {k: torch.zeros(1, c, FGRID.H, FGRID.W) for k, c in HEAD_CHANNELS.items()}
    maps["heatmap"] -= 10.0
    idx = (t.sample, slice(None), t.row, t.col)
    maps["heatmap"][t.sample, 0, t.row, t.col] = 5.0
    maps["offset"][idx] = t.offset
    maps["size"][idx] = t.log_size
    maps["yaw"][idx] = torch.stack([torch.sin(t.yaw), torch.cos(t.yaw)], dim=1)
    return maps


def test_targets_decode_back_to_the_boxes():
    rng = np.random.default_rng(0)
    xs = rng.choice(np.arange(-60.0, 60.0, 8.0), 12, replace=False) + rng.uniform(0, 1.5, 12)
    ys = rng.choice([-30.0, -10.0, 10.0, 30.0], 12) + rng.uniform(0, 1.5, 12)
    boxes = np.column_stack([xs, ys, np.full(12, 0.8), rng.uniform(3.5, 5.5, 12),
                             rng.uniform(1.7, 2.1, 12), np.full(12, 1.6),
                             rng.uniform(-np.pi, np.pi, 12)])
    out = decode(_perfect_maps(boxes), FGRID, np.zeros(1))[0]
    order = np.lexsort((out.boxes[:, 1], out.boxes[:, 0]))
    expect = boxes[np.lexsort((boxes[:, 1], boxes[:, 0]))]
    np.testing.assert_allclose(out.boxes[order], expect, atol=1e-5)


@pytest.mark.parametrize("fusion", ["gated", "max"])
def test_shipped_weights_match_their_checksum_and_load(detector, fusion):
    path = shipped_weights_path(fusion)
    assert path.stat().st_size <= 5 * 2**20
    assert sha256_of(path) == SHIPPED_SHA256[fusion]
    checkpoint = load_checkpoint(path)
    assert checkpoint.grid == GRID and "train-detector" in checkpoint.meta["command"]
    assert checkpoint.net.fusion == fusion
    assert detector.grid == GRID and detector.gate is not None  # the default: gated


def test_the_shipped_gate_was_trained_on_the_shipped_detector_left_unchanged():
    gated, plain = load_checkpoint(shipped_weights_path()), load_checkpoint(
        shipped_weights_path("max"))
    assert gated.meta["init_sha256"] == SHIPPED_SHA256["max"]
    assert "--freeze-detector" in gated.meta["command"]
    assert set(gated.state_dict) - set(plain.state_dict) == {
        f"gate.body.{k}.{p}" for k in (0, 2) for p in ("weight", "bias")}
    for name, value in plain.state_dict.items():
        assert torch.equal(gated.state_dict[name], value), name
    with pytest.raises(ValueError, match="shipped weights exist for fusion"):
        shipped_weights_path("attention")


def test_a_shifted_map_decodes_to_shifted_boxes(detector, scene):
    """Warping an encoder map by a pose moves its decoded boxes by that pose."""
    features = detector.encode(torch.from_numpy(scene.rasters[:1]))
    base = detector.decode(features, np.zeros(1))[0]
    for pose in (np.array([3.2, -4.8, 0.0]), np.array([2.0, 1.0, 0.15])):
        moved_maps = fuse_maps(torch.zeros_like(features).expand(2, -1, -1, -1).clone()
                               .index_copy(0, torch.tensor([1]), features),
                               [0], [[1]], [pose[None]], detector.feature_grid)
        moved = detector.decode(moved_maps, np.zeros(1))[0]
        expect = transform_boxes(base.boxes[base.scores > 0.3], pose)
        inside = (np.abs(expect[:, 0]) < 60.0) & (np.abs(expect[:, 1]) < 30.0)
        expect = expect[inside]
        assert expect.shape[0] >= 5
        dist = np.hypot(expect[:, None, 0] - moved.boxes[None, :, 0],
                        expect[:, None, 1] - moved.boxes[None, :, 1]).min(axis=1)
        # Whole-cell translations are exact; a rotation resamples the features (bilinear)
        # and the network is not rotation-equivariant: within a feature cell (1.6 m).
        assert np.median(dist) < (0.05 if pose[2] == 0.0 else 1.0)


def _fused_ap(detector, scene, error: np.ndarray) -> float:
    features = detector.encode(torch.from_numpy(scene.rasters))
    egos = [a for a, c in enumerate(scene.collaborators) if c]
    poses = [scene.relative[a] + error for a in egos]
    fused = fuse_maps(features, egos, [list(scene.collaborators[a]) for a in egos], poses,
                      detector.feature_grid)
    acc = APAccumulator((0.5,))
    for a, det in zip(egos, detector.decode(fused, scene.grounds[egos]), strict=True):
        acc.add_frame(det.boxes, det.scores, scene.group_eval_gt[a])
    return acc.ap()[0.5]


def test_a_wrong_pose_decodes_worse_than_the_true_pose(detector, scene):
    true_ap = _fused_ap(detector, scene, np.zeros(3))
    wrong_ap = _fused_ap(detector, scene, np.array([1.5, -1.0, np.deg2rad(3.0)]))
    assert true_ap > wrong_ap + 0.05


def test_training_smoke_run_lowers_the_loss_and_is_deterministic():
    from roco_env.training.detector_config import TrainConfig
    from roco_env.training.train import train

    config = TrainConfig(x_range=(-25.6, 25.6), y_range=(-12.8, 12.8), widths=(4, 8, 8),
                         train_scenes=2, val_scenes=0, steps=16, lr=1e-2,
                         scenarios=("urban_intersection",), threads=1)
    result = train(config, progress=False)
    total = result.history["total"]
    assert len(total) == 16 and np.mean(total[-4:]) < np.mean(total[:4])
    # Same seed, same machine: same weights, whether the batches come from workers or not.
    again = train(dataclasses.replace(config, workers=2), progress=False)
    for name, value in result.net.state_dict().items():
        assert torch.equal(value, again.net.state_dict()[name]), name


def test_fine_tuning_with_a_frozen_encoder_changes_only_the_trunk_and_heads(tmp_path):
    """A run from a weights file with train_encoder=False and the fused loss on a canvas
    beyond the detector grid: the encoder (weights and batch-norm statistics) is the
    file's, the trunk and heads moved, the loss fell."""
    from roco_env.training.detector_config import TrainConfig
    from roco_env.training.train import fused_canvas, train

    net, _, settings = tiny_detector_start(tmp_path)
    config = TrainConfig(**settings, steps=16, lr=1e-2, train_encoder=False,
                         fused_x_range=(-40.0, 40.0), fused_y_range=(-16.0, 16.0))
    assert (fused_canvas(config).W, fused_canvas(config).H) == (50, 20)
    result = train(config, progress=False)
    total = result.history["total"]
    assert np.mean(total[-4:]) < np.mean(total[:4])
    encoder = {f"{name}.": module for name, module in result.net.named_children()
               if module in result.net.encoder_modules()}
    before, after = net.state_dict(), result.net.state_dict()
    for name, value in after.items():
        frozen = name.startswith(tuple(encoder))
        assert torch.equal(value, before[name]) == frozen or "num_batches" in name, name
    assert "fused_ap50" in result.validation


def test_warp_augmentation_moves_maps_and_their_targets_alike():
    """With warp_augment=1 every single-agent map is warped and its targets moved: the
    plain batch's target heatmap, warped as the maps are, peaks on the moved targets."""
    from roco_env.geometry import se2_apply, se2_inverse
    from roco_env.training.data import TRAIN_SEED_BASE
    from roco_env.training.detector_config import TrainConfig
    from roco_env.training.train import _Batches, _warped, feature_grid_of

    config = TrainConfig(x_range=(-25.6, 25.6), y_range=(-12.8, 12.8), train_scenes=2,
                         steps=1, scenes_per_step=2, scenarios=("urban_intersection",),
                         warp_augment=1.0)
    scenes = make_scenes(config.scenarios, 2, TRAIN_SEED_BASE, config.grid, config.noise)
    moved = _Batches(scenes, config)[0]
    plain = _Batches(scenes, dataclasses.replace(config, warp_augment=0.0))[0]
    fgrid = feature_grid_of(config)
    n_maps = plain.rasters.shape[0]
    assert moved.warped.tolist() == list(range(n_maps)) and plain.warped.size == 0
    assert np.ptp(moved.warps[:, 2]) > 1.0 and np.abs(moved.warps[:, :2]).max() <= 1.6
    heat = _warped(plain.single.heatmap, moved, fgrid)[:, 0]
    t = moved.single
    centres = np.column_stack([fgrid.x_range[0] + (t.col.numpy() + 0.5) * 1.6,
                               fgrid.y_range[0] + (t.row.numpy() + 0.5) * 1.6])
    source = np.array([se2_apply(se2_inverse(moved.warps[k]), c)
                       for k, c in zip(t.sample.numpy(), centres, strict=True)])
    # Every moved target comes from the map (boxes off it have no features to move)...
    margin = 1.6 * np.sqrt(2.0)  # a target cell's centre is within a cell of the box's
    assert np.all(np.abs(source[:, 0]) < 25.6 + margin)
    assert np.all(np.abs(source[:, 1]) < 12.8 + margin)
    # ...and the warped heatmap peaks on it (away from the edges, where the warp blends
    # in the zero padding).
    inside = ((np.abs(source[:, 0]) < 25.6 - 1.6) & (np.abs(source[:, 1]) < 12.8 - 1.6))
    values = heat[t.sample, t.row, t.col].numpy()[inside]
    assert inside.sum() >= 10 and np.mean(values > 0.25) > 0.9


def test_train_detector_cli_records_a_two_stage_recipe(tmp_path, capsys):
    """Stage 1 from scratch, stage 2 fine-tuning it: the second weights record every option
    and the sha256 of the file they started from; a frozen encoder without --init is
    exit 2 with the reason."""
    from roco_env.cli import main

    tiny = ["--steps=2", "--train-scenes=1", "--val-scenes=0", "--scenes-per-step=1",
            "--widths", "4", "8", "8", "--scenarios", "highway_dense", "--threads=1", "--quiet"]
    assert main(["train-detector", "--out", str(tmp_path / "one"), *tiny]) == 0
    first = tmp_path / "one" / "bev_detector.pt"
    stage2 = ["--init", str(first), "--freeze-encoder", "--warp-augment=0.5",
              "--fused-x-range", "-100", "100", "--fused-y-range", "-40", "40"]
    assert main(["train-detector", "--out", str(tmp_path / "two"), *tiny, *stage2]) == 0
    meta = load_checkpoint(tmp_path / "two" / "bev_detector.pt").meta
    assert meta["init_sha256"] == sha256_of(first)
    for option in (f"--init={first}", "--freeze-encoder", "--warp-augment=0.5",
                   "--fused-x-range -100.0 100.0", "--fused-y-range -40.0 40.0"):
        assert option in meta["command"]
    assert f"sha256 `{sha256_of(first)}`" in (tmp_path / "two" / "report.md").read_text()
    history = json.loads((tmp_path / "two" / "loss_history.json").read_text())
    assert len(history["total"]) == 2  # per step: the loss picture can be redrawn
    capsys.readouterr()
    for bad, message in ((["--freeze-encoder"], "(a frozen encoder, --freeze-encoder) needs "
                                                "init, the weights file to start from (--init"),
                         (["--warp-augment=2"], "warp_augment=2.0 is out of range; allowed "
                                                "[0.0, 1.0]"),
                         (["--fused-x-range", "5", "-5"], "low < high, in m (--fused-x-range"),
                         (["--init", str(first), "--widths", "4", "8", "4"],
                          "were trained with widths (4, 8, 8)")):
        out = tmp_path / "three"
        assert main(["train-detector", "--out", str(out), *tiny, *bad]) == 2
        assert message in capsys.readouterr().err and not out.exists()


def test_fine_tuning_inputs_are_checked(tmp_path):
    from roco_env.schema import build
    from roco_env.training.detector_config import WHERE, TrainConfig
    from roco_env.training.train import train

    with pytest.raises(ValueError, match="train_encoder=False .* needs init"):
        TrainConfig(train_encoder=False)
    with pytest.raises(ValueError, match="fused_x_range must be None or two finite numbers"):
        TrainConfig(fused_x_range=(40.0, -40.0))
    with pytest.raises(ValueError, match=r"train-detector: warp_augment=1.5 is out of range; "
                                         r"allowed \[0.0, 1.0\]"):
        build(TrainConfig, {"warp_augment": 1.5}, WHERE)
    start = tmp_path / "start.pt"
    save_checkpoint(start, BevDetectorNet(NetConfig(widths=(4, 8, 8))), GRID, ScanNoise(), {})
    for change, field in (({"widths": (4, 8, 4)}, "widths"),
                          ({"widths": (4, 8, 8), "x_range": (-25.6, 25.6)}, "grid")):
        config = TrainConfig(train_scenes=1, val_scenes=0, steps=1, init=str(start), **change)
        with pytest.raises(ValueError, match=f"init weights .* were trained with {field}"):
            train(config, progress=False)
    with pytest.raises(ValueError, match="does not exist"):
        train(TrainConfig(init=str(tmp_path / "missing.pt"), train_scenes=1), progress=False)


def _episode(seed: int):
    env = roco_env.parallel_env("urban_intersection", max_cycles=2, detector="learned",
                                fusion="intermediate", density=2.0)
    obs, _ = env.reset(seed=seed)
    out = [obs["cav_0"]["boxes"].copy()]
    while env.agents:
        obs, rewards, _, _, infos = env.step({a: np.zeros((5, 3)) for a in env.agents})
        out += [obs["cav_0"]["boxes"].copy(), infos["cav_0"]["fused_boxes"],
                np.array(list(rewards.values()))]
    return out


def test_same_seed_same_episode_with_the_learned_detector():
    a, b = _episode(5), _episode(5)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    assert any(x.size for x in a[1::3])  # it detected something


def test_learned_detector_reports_its_uncertainty(detector, scene):
    det = detector.decode(detector.encode(torch.from_numpy(scene.rasters[:1])), np.zeros(1))[0]
    assert det.boxes.shape[0] > 0 and det.uncertainty.shape == (det.boxes.shape[0], 3)
    assert np.all(det.uncertainty > 0) and np.all(np.isfinite(det.uncertainty))


def _payload(tmp_path, **changes):
    path = tmp_path / "w.pt"
    save_checkpoint(path, BevDetectorNet(NetConfig(widths=(4, 8, 8))), GRID, ScanNoise(), {})
    payload = torch.load(path, weights_only=True)
    payload.update(changes)
    torch.save(payload, path)
    return path


def test_bad_weights_files_raise_clear_errors(tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        LearnedDetector(tmp_path / "missing.pt")
    with pytest.raises(ValueError, match="is not a file"):
        LearnedDetector(tmp_path)
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(b"not a checkpoint" * 10)
    with pytest.raises(ValueError, match="is corrupt") as error:
        LearnedDetector(corrupt)
    assert "weights_only" not in str(error.value)
    with pytest.raises(ValueError, match=r"raster channels \['a', 'b', 'c'\] \(3\)"):
        LearnedDetector(_payload(tmp_path, channels=["a", "b", "c"]))
    with pytest.raises(ValueError, match="expects 3 input channels"):
        LearnedDetector(_payload(tmp_path, net={"in_channels": 3, "widths": [4, 8, 8]}))
    with pytest.raises(ValueError, match="must be multiples of 4"):
        LearnedDetector(_payload(tmp_path, grid={"x_range": [-70.0, 70.0],
                                                 "y_range": [-40.0, 40.0], "resolution": 0.8}))
    with pytest.raises(ValueError, match="does not match its declared network"):
        LearnedDetector(_payload(tmp_path, net={"in_channels": len(LIDAR_CHANNELS), "widths": [8, 8, 8]}))
    with pytest.raises(ValueError, match="not a roco-env BEV detector"):
        LearnedDetector(_payload(tmp_path, format="something else"))


def test_learned_detector_options_are_checked():
    with pytest.raises(ValueError, match="unknown key 'detector.params.sigma_xy'; allowed: detector.params.weights"):
        roco_env.parallel_env(detector="learned", **{"detector.params": {"sigma_xy": 0.1}})
    with pytest.raises(ValueError, match=r"device='tpu' is not allowed; choose one of \['cpu', 'cuda'\]"):
        roco_env.parallel_env(detector="learned", **{"detector.params": {"device": "tpu"}})
    with pytest.raises(ConfigError, match="needs detector.preset='learned'"):
        roco_env.parallel_env(fusion="intermediate")


@pytest.mark.parametrize("policy", [
    pytest.param(name, marks=() if name == "roco" else pytest.mark.slow)
    for name in available_policies()])
@pytest.mark.parametrize("fusion", ["late", "intermediate"])
def test_every_policy_runs_with_the_learned_detector(policy, fusion):
    act = make_policy(policy)
    env = roco_env.parallel_env("urban_intersection", max_cycles=2, **merge_env_overrides(
        {"detector": "learned", "fusion": fusion, "density": 2.0, "sigma_t": 0.4,
         "sigma_r": 0.4}, act))  # in the env modes the policy acts in (a learned one's)
    obs, infos = env.reset(seed=1)
    while env.agents:
        obs, rewards, _, _, infos = env.step({a: act(obs[a], infos[a]) for a in env.agents})
        assert all(0.0 <= r <= 1.0 for r in rewards.values())
        assert all(np.isfinite(infos[a]["ap70"]) or infos[a]["n_gt"] == 0 for a in infos)


def test_fusion_canvas_covers_the_evaluation_range_in_whole_cells():
    canvas, pads = fusion_canvas(FGRID, (-140.8, 140.8), (-40.0, 40.0))
    assert pads == (44, 44, 0, 0) and (canvas.H, canvas.W) == (FGRID.H, FGRID.W + 88)
    canvas, pads = fusion_canvas(FGRID, (-10.0, 100.0), (-41.0, 20.0))
    assert pads == (0, 19, 1, 0) and canvas.x_range[1] >= 100.0 and canvas.y_range[0] <= -41.0


def test_fuse_maps_is_each_egos_maximum_over_its_own_and_warped_maps():
    grid = BevGrid((-8.0, 8.0), (-4.0, 4.0), 1.0)
    features = torch.rand(4, 3, grid.H, grid.W, generator=torch.Generator().manual_seed(0))
    collaborators = [[1, 2, 3], [], [0], [0, 1]]  # unequal counts, one ego alone
    rng = np.random.default_rng(0)
    poses = [rng.normal(size=(len(c), 3)) * [2.0, 1.0, 0.3] for c in collaborators]
    for fuse in (fuse_maps, fuse_on_canvas):
        fused = fuse(features, [0, 1, 2, 3], collaborators, poses, grid)
        for e, (c, p) in enumerate(zip(collaborators, poses, strict=True)):
            expected = features[e]
            for j, pose in zip(c, p, strict=True):
                expected = torch.maximum(expected, warp_bev(features[j], pose, grid))
            torch.testing.assert_close(fused[e], expected, rtol=1e-5, atol=1e-5)


def test_compiled_fusion_agrees_with_the_torch_path():
    """fuse_on_canvas on float32 CPU maps (the compiled warp-and-max loop) against its torch
    path (grid_sample, taken for float64 maps): detector-sized maps, far rotated poses."""
    grid = BevGrid((-70.4, 70.4), (-40.0, 40.0), 1.6)
    canvas, _ = fusion_canvas(grid, (-140.8, 140.8), (-40.0, 40.0))
    features = torch.rand(5, 8, grid.H, grid.W, generator=torch.Generator().manual_seed(3))
    features = features.contiguous(memory_format=torch.channels_last)
    collaborators = [[1, 2, 3, 4], [0, 2], [], [4], [3, 0, 1]]
    rng = np.random.default_rng(5)
    poses = [rng.normal(size=(len(c), 3)) * [40.0, 15.0, 1.5] for c in collaborators]
    fast = fuse_on_canvas(features, range(5), collaborators, poses, grid, canvas)
    reference = fuse_on_canvas(features.double(), range(5), collaborators, poses, grid, canvas)
    assert fast.dtype == torch.float32 and fast.is_contiguous(memory_format=torch.channels_last)
    assert not torch.equal(fast[0], torch.nn.functional.pad(features[0], (44, 44)))  # warped in
    torch.testing.assert_close(fast.double(), reference, rtol=1e-5, atol=1e-5)


def test_fusing_onto_a_larger_canvas_equals_fusing_zero_padded_maps():
    grid = BevGrid((-8.0, 8.0), (-4.0, 4.0), 1.0)
    canvas, pads = fusion_canvas(grid, (-12.0, 10.0), (-6.0, 4.0))
    features = torch.rand(3, 2, grid.H, grid.W, generator=torch.Generator().manual_seed(1))
    collaborators = [[1, 2], [0]]
    poses = [np.array([[3.0, -1.0, 0.4], [-2.5, 0.5, -1.2]]), np.array([[1.5, 2.0, 2.8]])]
    direct = fuse_on_canvas(features, [0, 1], collaborators, poses, grid, canvas)
    padded = fuse_maps(torch.nn.functional.pad(features, pads), [0, 1], collaborators, poses,
                       canvas)
    torch.testing.assert_close(direct, padded, rtol=1e-5, atol=1e-5)
    # The training path (differentiable) onto the canvas gives the same maps.
    trained = fuse_maps(features, [0, 1], collaborators, poses, grid, canvas)
    torch.testing.assert_close(trained, padded, rtol=1e-5, atol=1e-5)
    shifted = BevGrid((-12.5, 9.5), (-6.0, 4.0), 1.0)
    with pytest.raises(ValueError, match="must contain the feature grid"):
        fuse_on_canvas(features, [0], [[1]], [poses[1]], grid, shifted)


def test_learned_detector_parameters_are_checked_by_the_scenario_schema():
    """make_learned_detector and the constructor check against LearnedDetectorParams."""
    with pytest.raises(ValueError, match="unknown key 'detector.params.sigma_xy'"):
        make_learned_detector({"sigma_xy": 0.1})
    for threads in (0, 1.5, True):
        with pytest.raises(ValueError, match="detector.params.threads"):
            make_learned_detector({"threads": threads})
    for threshold in (0.0, 1.0, float("nan"), "high"):
        with pytest.raises(ValueError, match="detector.params.score_threshold"):
            make_learned_detector({"score_threshold": threshold})
    with pytest.raises(ValueError, match=r"detector.params.device='tpu' is not allowed"):
        LearnedDetector(device="tpu")
    with pytest.raises(ValueError, match="detector.params.threads=0 is out of range"):
        LearnedDetector(threads=0)


@pytest.mark.parametrize("given, expected", [({}, 1), ({"threads": 3}, 3)])
def test_learned_detector_threads_are_set_process_wide(given, expected):
    """One thread by default (threads lose many times over on a busy CPU); a given count is
    set as torch's, and intermediate fusion runs that many bands."""
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        detector = LearnedDetector(**given)
        assert detector.threads == expected == torch.get_num_threads()
    finally:
        torch.set_num_threads(before)


def test_decoding_peaks_use_the_3x3_maximum_of_max_pool():
    maps = torch.rand(3, 7, 11, generator=torch.Generator().manual_seed(2))
    maps[0, 2:5, 3:6] = 0.5  # a plateau: ties everywhere
    expected = torch.nn.functional.max_pool2d(maps[:, None], 3, 1, 1)[:, 0]
    assert torch.equal(_max_3x3(maps), expected)


@pytest.mark.parametrize("scenario", ["dair_like", "v2xset_like"])
def test_axial_headings_of_one_object_agree_between_ego_and_collaborator(scenario):
    """The learned detector knows headings up to pi: the env hands the ego's boxes and its
    collaborators' boxes over in one world-anchored half-turn, so that the same object,
    seen by the ego and by a collaborator, has one heading in the ego's frame (through the
    reported, noisy relative pose); a flip would break RoCo's edge similarity. Both
    scenes have an RSU, which faces the diagonal of its crossing."""
    from roco_env.env import CollabPerceptionEnv

    env = CollabPerceptionEnv(scenario=scenario, max_cycles=3, detector="learned",
                              sigma_t=0.4, sigma_r=0.4)
    agree = flipped = 0
    for seed in range(2):
        env.reset(seed=seed)
        for _ in range(3):
            for view in env._frame.views:
                mine = dict(zip(view.object_ids.tolist(), view.boxes[:, 6], strict=True))
                for rel, boxes, ids in zip(view.reported_relative, view.collab_boxes,
                                           view.collab_object_ids, strict=True):
                    for obj, yaw in zip(ids.tolist(), boxes[:, 6] + rel[2], strict=True):
                        if obj >= 0 and obj in mine:
                            gap = abs(np.mod(yaw - mine[obj] + np.pi / 2, np.pi) - np.pi / 2)
                            turned = abs(np.mod(yaw - mine[obj] + np.pi, 2 * np.pi) - np.pi)
                            agree += turned < np.pi / 2
                            flipped += turned >= np.pi / 2 and gap < np.pi / 4
            env.step({a: np.zeros((env.config.max_collaborators, 3))
                      for a in env.possible_agents})
    assert agree > 30 and flipped <= 0.03 * (agree + flipped)


def test_assessment_reports_fusion_inside_and_beyond_the_detector_grid(tmp_path):
    """The learned assessment on a one-step episode: every setting, the region split of
    both fusions, and the sha256 of the weights it was given."""
    import json

    from roco_env.training.assessment import main as assessment

    weights = tmp_path / "copy.pt"
    weights.write_bytes(shipped_weights_path().read_bytes())
    assert assessment(["--seeds", "1", "--steps", "1", "--out", str(tmp_path),
                       "--weights", str(weights)]) == 0
    result = json.loads((tmp_path / "assessment.json").read_text())
    assert result["weights_sha256"] == SHIPPED_SHA256["gated"] and "--weights" in result["command"]
    for fusion in ("late", "intermediate"):
        values = result[f"{fusion}_learned_true_poses"]
        for region in ("inside_grid", "beyond_grid"):
            assert 0.0 <= values[f"{region}_ap50"] <= 1.0
        assert values["inside_grid_ap50"] >= values["beyond_grid_ap50"]
    assert "beyond AP@0.7" in (tmp_path / "assessment.md").read_text()
    # A whole-cell shift moves the map exactly: the decoded boxes move with it.
    whole, half = result["warp_consistency"]["whole cells"], result["warp_consistency"]["half turn"]
    assert whole["n"] > 20 and whole["p90_x"] < 1e-4 and whole["p90_y"] < 1e-4
    assert half["n"] > 20 and np.isfinite(half["median_y"])
