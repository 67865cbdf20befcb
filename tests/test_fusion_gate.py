"""The learned fusion gate: fusion paths, training of the gate alone, weights files."""

from __future__ import annotations

import multiprocessing
import os

import numpy as np
import pytest
import torch
from conftest import tiny_detector_start

import roco_env
from roco_env.fusion.intermediate import fuse_maps, fuse_on_canvas, fusion_canvas
from roco_env.sensing import BevGrid
from roco_env.sensing.learned import BevDetectorNet, LearnedDetector, NetConfig, save_checkpoint
from roco_env.sensing.learned.model import load_checkpoint
from roco_env.sensing.learned.network import FusionGate
from roco_env.sensing.lidar import ScanNoise

GRID = BevGrid((-70.4, 70.4), (-40.0, 40.0), 1.6)
COLLABORATORS = [[1, 2, 3, 4], [0, 2], [], [4], [3, 0, 1]]


def _maps_and_poses(channels: int = 8):
    features = torch.rand(5, channels, GRID.H, GRID.W, generator=torch.Generator().manual_seed(3))
    rng = np.random.default_rng(5)
    poses = [rng.normal(size=(len(c), 3)) * [40.0, 15.0, 1.5] for c in COLLABORATORS]
    return features.contiguous(memory_format=torch.channels_last), poses


def _gate(channels: int, bias: float | None = None) -> FusionGate:
    """A gate with random weights (weights far from 1 and 0 alike), or a constant one."""
    torch.manual_seed(0)
    gate = FusionGate(channels)
    with torch.no_grad():
        if bias is None:
            for parameter in gate.parameters():
                parameter.normal_(0.0, 0.5)
        else:
            gate.body[2].weight.zero_()
            gate.body[2].bias.fill_(bias)
    return gate.eval()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_run_time_gated_fusion_equals_the_training_path(dtype):
    """fuse_on_canvas (windows, in place, the gate read against each ego's own map before any
    maximum; compiled warps for float32 CPU maps, grid_sample otherwise) against fuse_maps
    (whole canvas, differentiable), far rotated poses."""
    features, poses = _maps_and_poses()
    features = features.to(dtype)
    canvas, _ = fusion_canvas(GRID, (-140.8, 140.8), (-40.0, 40.0))
    gate = _gate(8).to(dtype)
    with torch.no_grad():
        run_time = fuse_on_canvas(features, range(5), COLLABORATORS, poses, GRID, canvas, gate)
        training = fuse_maps(features, range(5), COLLABORATORS, poses, GRID, canvas, gate)
        plain = fuse_maps(features, range(5), COLLABORATORS, poses, GRID, canvas)
        weights = gate(features[:1], features[1:2])
    assert run_time.dtype == dtype
    assert float(weights.min()) < 0.5 < float(weights.max())  # it passes some, drops some
    torch.testing.assert_close(run_time, training, rtol=1e-5, atol=1e-5)
    assert (plain - training).abs().max() > 0.1  # and it changes the fused maps


@pytest.mark.parametrize("gated", [False, True])
def test_the_compiled_fusion_gives_the_same_maps_on_any_thread_count(gated):
    """Bands of canvas rows in threads (the kernels release the GIL): every cell sees the
    maps in the same order, so the maps are equal bit for bit, with more threads than rows
    too."""
    features, poses = _maps_and_poses()
    canvas, _ = fusion_canvas(GRID, (-140.8, 140.8), (-40.0, 40.0))
    gate = _gate(8) if gated else None
    with torch.no_grad():
        one = fuse_on_canvas(features, range(5), COLLABORATORS, poses, GRID, canvas, gate)
        for threads in (2, 3, canvas.H + 5):
            many = fuse_on_canvas(features, range(5), COLLABORATORS, poses, GRID, canvas, gate,
                                  threads)
            assert torch.equal(many, one), threads
    assert one.abs().sum() > 0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("threads", [0, -1, 1.5, True, None])
def test_the_fusion_thread_count_is_checked(threads, dtype):
    """On every path: the compiled pass and grid_sample (float64) alike."""
    features, poses = _maps_and_poses()
    with pytest.raises(ValueError, match="threads must be an integer >= 1"):
        fuse_on_canvas(features.to(dtype), range(5), COLLABORATORS, poses, GRID, GRID, None,
                       threads)


def _fuse_in_forked_child(features, poses, canvas, expected) -> None:
    """A sweep worker's situation: forked after the parent fused in threads."""
    torch.set_num_threads(1)  # as the sweep's workers do (torch's threads do not survive a fork)
    with torch.no_grad():
        fused = fuse_on_canvas(features, range(5), COLLABORATORS, poses, GRID, canvas, None, 2)
    os._exit(0 if torch.equal(fused, expected) else 3)


def test_a_forked_child_fuses_in_threads_after_its_parent_did():
    """The parent's fusion threads do not exist in a forked child: it must start its own
    instead of queueing the bands on the parent's pool and waiting forever."""
    features, poses = _maps_and_poses()
    canvas, _ = fusion_canvas(GRID, (-140.8, 140.8), (-40.0, 40.0))
    with torch.no_grad():
        expected = fuse_on_canvas(features, range(5), COLLABORATORS, poses, GRID, canvas, None, 2)
    child = multiprocessing.get_context("fork").Process(
        target=_fuse_in_forked_child, args=(features, poses, canvas, expected))
    child.start()
    child.join(timeout=60)
    if child.is_alive():
        child.kill()
        child.join()
        pytest.fail("the forked child hung in the threaded fusion")
    assert child.exitcode == 0


@pytest.mark.parametrize("bias, expected", [(30.0, "max"), (-30.0, "own")])
def test_an_open_gate_is_max_fusion_and_a_closed_one_keeps_the_egos_maps(bias, expected):
    features, poses = _maps_and_poses()
    canvas, pads = fusion_canvas(GRID, (-140.8, 140.8), (-40.0, 40.0))
    with torch.no_grad():
        gated = fuse_on_canvas(features, range(5), COLLABORATORS, poses, GRID, canvas,
                               _gate(8, bias))
        reference = (fuse_on_canvas(features, range(5), COLLABORATORS, poses, GRID, canvas)
                     if expected == "max" else torch.nn.functional.pad(features, pads))
    torch.testing.assert_close(gated, reference, rtol=1e-5, atol=1e-5)


def test_a_gated_weights_file_round_trips_and_old_files_read_as_max(tmp_path):
    grid = BevGrid((-25.6, 25.6), (-12.8, 12.8), 0.8)
    gated, plain = tmp_path / "gated.pt", tmp_path / "plain.pt"
    net = BevDetectorNet(NetConfig(widths=(4, 8, 8), fusion="gated"))
    save_checkpoint(gated, net, grid, ScanNoise(), {})
    save_checkpoint(plain, BevDetectorNet(NetConfig(widths=(4, 8, 8))), grid, ScanNoise(), {})
    assert load_checkpoint(gated).net.fusion == "gated"
    assert LearnedDetector(gated).gate is not None and LearnedDetector(plain).gate is None
    assert LearnedDetector(gated, gate=False).gate is None  # the plain maximum, for ablations
    with pytest.raises(ValueError, match="holds no fusion gate"):
        LearnedDetector(plain, gate=True)
    with pytest.raises(ValueError, match="detector.params.gate"):
        LearnedDetector(gated, gate="yes")
    payload = torch.load(plain, weights_only=True)
    del payload["net"]["fusion"]  # a file written before the gate existed
    torch.save(payload, plain)
    assert load_checkpoint(plain).net.fusion == "max"
    with pytest.raises(ValueError, match="NetConfig.fusion must be one of"):
        NetConfig(fusion="attention")


def test_training_the_gate_alone_changes_only_the_gate(tmp_path):
    """--freeze-detector from a gate-less file: the detector (weights and batch-norm
    statistics) is the file's, the fresh gate (its output bias starts at 4) moved."""
    from roco_env.training.detector_config import TrainConfig
    from roco_env.training.train import train

    net, _, settings = tiny_detector_start(tmp_path)
    config = TrainConfig(**settings, steps=8, lr=3e-2, fusion="gated", train_detector=False,
                         pose_sigma_t=0.8, pose_sigma_r=0.8)
    result = train(config, progress=False)
    before, after = net.state_dict(), result.net.state_dict()
    assert set(after) - set(before) == {f"gate.body.{k}.{p}" for k in (0, 2)
                                        for p in ("weight", "bias")}
    for name, value in before.items():
        assert torch.equal(after[name], value), name
    assert float(after["gate.body.2.bias"]) != 4.0
    assert "fused_ap50" in result.validation


def test_gate_training_inputs_are_checked(tmp_path):
    from roco_env.schema import build
    from roco_env.training.detector_config import WHERE, TrainConfig
    from roco_env.training.train import train

    with pytest.raises(ValueError, match=r"fusion='mean' is not allowed; choose one of "
                                         r"\['max', 'gated'\]"):
        build(TrainConfig, {"fusion": "mean"}, WHERE)
    with pytest.raises(ValueError, match="--freeze-detector.* needs init"):
        TrainConfig(train_detector=False, fusion="gated")
    start = tmp_path / "gated.pt"
    save_checkpoint(start, BevDetectorNet(NetConfig(fusion="gated")),
                    BevGrid((-70.4, 70.4), (-40.0, 40.0), 0.8), ScanNoise(), {})
    with pytest.raises(ValueError, match="--fusion gated"):
        TrainConfig(train_detector=False, init=str(start))
    with pytest.raises(ValueError, match="hold a fusion gate; this run's fusion is 'max'"):
        train(TrainConfig(init=str(start), train_scenes=1, val_scenes=0, steps=1),
              progress=False)


@pytest.mark.parametrize("fusion", ["late", "none"])
@pytest.mark.parametrize("gate", [True, False])
def test_a_gate_choice_without_intermediate_fusion_is_refused(gate, fusion):
    with pytest.raises(ValueError, match=f"needs fusion.method='intermediate'; got "
                       f"fusion.method='{fusion}' \\(with it leave the gate unset"):
        roco_env.parallel_env("v2x_crossroad", detector="learned", fusion=fusion,
                              **{"detector.params.gate": gate})


def test_a_gate_for_other_maps_is_refused():
    features, poses = _maps_and_poses(channels=8)
    with torch.no_grad(), pytest.raises(ValueError, match="reads 6 channels; the maps have 8"):
        fuse_on_canvas(features, range(5), COLLABORATORS, poses, GRID, gate=_gate(6))


@pytest.mark.parametrize("gated", [False, True])
def test_maps_moved_off_the_canvas_leave_the_egos_own(gated):
    """A correction can move every collaborator's map past the canvas (a policy's action is
    applied as given): fusion then keeps each ego's own map, on the compiled pass and the
    training path alike (it once failed building a one-column window)."""
    features, poses = _maps_and_poses()
    canvas, pads = fusion_canvas(GRID, (-140.8, 140.8), (-40.0, 40.0))
    far = [np.column_stack([np.full(len(p), 400.0), p[:, 1:]]) for p in poses]
    gate = _gate(8) if gated else None
    with torch.no_grad():
        run_time = fuse_on_canvas(features, range(5), COLLABORATORS, far, GRID, canvas, gate)
        training = fuse_maps(features, range(5), COLLABORATORS, far, GRID, canvas, gate)
    own = torch.nn.functional.pad(features, pads)
    torch.testing.assert_close(run_time, own)
    torch.testing.assert_close(training, own)
