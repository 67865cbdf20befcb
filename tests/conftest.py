"""Shared test setup and helpers: headless plotting, the `slow` marker policy,
hand-built scenes for the sensing tests, a stand-in sweep cell for the bench tests,
stages registered for one test, digests of whole episodes and the references compiled
kernels are compared with (to rounding; RoCo's assignment).

Tests marked ``@pytest.mark.slow`` run only when ROCO_SLOW=1; the default run
(and CI) keeps a representative fast sample so the suite stays well under ten
minutes on a 2-core machine. Test modules take the helpers from here
(``from conftest import car, make_state``), never from one another.
"""

import hashlib
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
import pytest
from hypothesis import settings
from scipy.optimize import linear_sum_assignment

import roco_env
from roco_env import stages
from roco_env.sweeps.cells import Cell
from roco_env.sweeps.records import ok_record
from roco_env.traffic.state import WorldState

# CI (CI=true) replays the same examples every run so a green main stays green;
# local runs keep exploring new random examples (and the example database).
settings.register_profile("ci", derandomize=True, database=None, print_blob=True)
if os.environ.get("CI", "").lower() == "true":
    settings.load_profile("ci")

matplotlib.use("Agg")
os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
os.environ.setdefault("MPLBACKEND", "Agg")


def pytest_collection_modifyitems(config, items):
    if os.environ.get("ROCO_SLOW") == "1":
        return
    skip = pytest.mark.skip(reason="slow; run with ROCO_SLOW=1")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)


@pytest.fixture
def registered():
    """Registers stages (``registered(kind, name, factory, params)``) that are forgotten
    after the test."""
    added: list[tuple[str, str]] = []

    def register(kind, name, factory, params=None):
        roco_env.register_stage(kind, name, factory, params)
        added.append((kind, name))

    yield register
    for kind, name in added:
        stages.unregister_stage(kind, name)


def run_python(code: str) -> str:
    """Stdout (stripped) of ``code`` run by a fresh interpreter in the repository root:
    what a new process imports, untouched by modules this test session loaded."""
    done = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True,
                          text=True, cwd=Path(__file__).resolve().parents[1])
    return done.stdout.strip()


# --- Hand-built scenes (sensing tests) -----------------------------------------------

CAR_SIZE = (4.5, 1.9, 1.5)


def car(x: float, y: float, yaw: float = 0.0) -> list[float]:
    length, width, height = CAR_SIZE
    return [x, y, height / 2, length, width, height, yaw]


def bus(x: float, y: float, yaw: float = 0.0) -> list[float]:
    return [x, y, 1.6, 12.0, 2.6, 3.2, yaw]


def make_state(boxes, poses, kinds=None, own_ids=None, heights=None, ranges=None,
               comm_ranges=None) -> WorldState:
    """A hand-built WorldState: objects get ids 0..M-1; agents default to CAVs at 1.9 m."""
    boxes = np.asarray(boxes, dtype=float).reshape(-1, 7)
    poses = np.asarray(poses, dtype=float).reshape(-1, 3)
    n_agents, n_obj = poses.shape[0], boxes.shape[0]
    kinds = tuple(kinds or ("cav",) * n_agents)
    default_height = [5.5 if k == "rsu" else 1.9 for k in kinds]
    return WorldState(
        time=0.0,
        object_ids=np.arange(n_obj),
        object_classes=np.zeros(n_obj, dtype=np.int64),
        object_boxes=boxes,
        object_velocities=np.zeros((n_obj, 2)),
        agent_ids=tuple(f"{k}_{i}" for i, k in enumerate(kinds)),
        agent_kinds=kinds,
        agent_poses=poses,
        agent_object_ids=np.asarray(own_ids if own_ids is not None else [-1] * n_agents),
        sensor_heights=np.asarray(heights if heights is not None else default_height, float),
        sensor_ranges=np.asarray(ranges if ranges is not None else [70.0] * n_agents, float),
        comm_ranges=np.asarray(comm_ranges if comm_ranges is not None else [70.0] * n_agents,
                               float),
    )


# --- A stand-in sweep cell (bench tests) ---------------------------------------------

CALLS: list[str] = []
FAILING_NOISE: set[float] = set()


def fake_cell(cell: Cell) -> dict:
    """Deterministic stand-in for an episode; raises for noise levels in FAILING_NOISE."""
    CALLS.append(cell.key)
    if cell.noise in FAILING_NOISE:
        raise RuntimeError(f"boom at noise {cell.noise}")
    rng = np.random.default_rng([cell.seed, int(cell.noise * 10)])
    errors = np.abs(rng.normal(cell.noise, 0.1, size=(20, 2)))
    metrics = {"ap30": 0.9 - cell.noise / 2, "ap50": 0.8 - cell.noise / 2,
               "ap70": float(0.7 - cell.noise / 2 + 0.01 * cell.seed)}
    samples = {"before": errors.tolist(), "after": (errors / 10).tolist()}
    return ok_record(cell, metrics, samples, 0.0)


def tiny_detector_start(tmp_path: Path):
    """A tiny gate-less detector (widths 4 / 8 / 8, 51.2 m x 25.6 m grid) saved as a start
    file, and the TrainConfig settings of a quick run from it (torch loaded on call).
    Returns (network, file, settings)."""
    from roco_env.sensing import BevGrid
    from roco_env.sensing.learned import BevDetectorNet, NetConfig, save_checkpoint
    from roco_env.sensing.lidar import ScanNoise

    grid = BevGrid((-25.6, 25.6), (-12.8, 12.8), 0.8)
    start = tmp_path / "start.pt"
    net = BevDetectorNet(NetConfig(widths=(4, 8, 8)))
    save_checkpoint(start, net, grid, ScanNoise(), {})
    settings = dict(x_range=grid.x_range, y_range=grid.y_range, widths=(4, 8, 8),
                    train_scenes=2, val_scenes=1, scenarios=("urban_intersection",),
                    threads=1, init=str(start))
    return net, start, settings


def assert_equal_to_rounding(got, expected, rtol: float = 1e-12, err_msg: str = "") -> None:
    """A compiled (numba) float result against the numpy path it replaces, to rounding.

    The two evaluate the same formula but not with the same elementary functions: the
    compiled loops call libm's exp / sin / cos / atan2, numpy's ufuncs (and BLAS) pick
    SIMD versions by CPU (AVX-512 ones differ from libm by an ulp), so results may differ
    in the last bits on some x86-64 CPUs. Relative tolerance ``rtol``, absolute
    ``rtol`` times the reference's largest magnitude (at least 1): a value that cancels
    to near zero keeps the rounding of its larger inputs. NaN equals NaN; shapes must
    match. Discrete outcomes (indices, counts, choices) are compared exactly instead.
    """
    expected = np.asarray(expected, dtype=float)
    finite = np.abs(expected[np.isfinite(expected)])
    atol = rtol * max(1.0, float(finite.max(initial=0.0)))
    np.testing.assert_allclose(got, expected, rtol=rtol, atol=atol, err_msg=err_msg)


def kuhn_munkres_matches(cand_p, cand_q, score, tau1: float):
    """RoCo's assignment by scipy, the reference of the compiled one
    (``pose_kernels.scored_pairs``): the maximum-weight one-to-one assignment over the
    candidate pairs (landmark cand_p, box cand_q, sorted by landmark) with scores (C,),
    0 elsewhere; assigned candidate pairs with S >= tau1 are the matches (landmark (P,),
    box (P,), S (P,)), always by the solver (the compiled one takes a shortcut)."""
    rows, row_idx = np.unique(cand_p, return_inverse=True)
    cols, col_idx = np.unique(cand_q, return_inverse=True)
    weights = np.zeros((rows.size, cols.size))
    weights[row_idx, col_idx] = score
    valid = np.zeros_like(weights, dtype=bool)
    valid[row_idx, col_idx] = True
    r, c = linear_sum_assignment(weights, maximize=True)
    keep = valid[r, c] & (weights[r, c] >= tau1)
    return rows[r[keep]], cols[c[keep]], weights[r[keep], c[keep]]


def _feed(digest: Any, value: object) -> None:
    """Every number, array and text of ``value`` (nested dicts by sorted key) into the digest."""
    if isinstance(value, dict):
        for key in sorted(value, key=str):
            digest.update(str(key).encode())
            _feed(digest, value[key])
    elif isinstance(value, (list, tuple)):
        digest.update(f"[{len(value)}".encode())
        for item in value:
            _feed(digest, item)
    elif isinstance(value, (np.ndarray, np.generic, float, int, bool)):
        array = np.asarray(value)
        digest.update(f"{array.dtype}{array.shape}".encode())
        digest.update(np.ascontiguousarray(array).tobytes())
    else:
        digest.update(repr(value).encode())


def episode_digest(scenario: str, overrides: dict, seed: int, steps: int) -> str:
    """sha256 of a seeded episode's observations, rewards and infos (zero actions in the
    correction mode, the first choice in select mode)."""
    env = roco_env.parallel_env(scenario, max_cycles=steps, **overrides)
    digest = hashlib.sha256()
    observations, infos = env.reset(seed=seed)
    _feed(digest, [observations, infos])
    while env.agents:
        actions = {a: np.zeros(env.action_space(a).shape, dtype=env.action_space(a).dtype)
                   for a in env.agents}
        _feed(digest, env.step(actions))
    return digest.hexdigest()
