"""Sweep results you can trust: bad records are skipped and recomputed, every
file a cell reads is in its provenance, one sweep per output folder, workers die with a
killed sweep, and the time per call is a warm one."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import CALLS, FAILING_NOISE, fake_cell
from test_sweeps_sweep import _alive, _children

from roco_env.cli import main
from roco_env.sweeps import provenance
from roco_env.sweeps.cells import Cell, build_grid
from roco_env.sweeps.store import ResultsInUse, ResultStore
from roco_env.sweeps.sweep import run_sweep
from roco_env.sweeps.sweep_report import write_report


@pytest.fixture(autouse=True)
def _reset_fake():
    CALLS.clear()
    FAILING_NOISE.clear()


def _grid(seeds=(0, 1)):
    return build_grid(["s"], noises=[0.0, 0.4], policies=["identity"], seeds=list(seeds),
                      steps=2)


# --- Readable but bad records (item 6) -------------------------------------------------


def _edited(line: str, edit) -> str:
    record = json.loads(line)
    edit(record)
    return json.dumps(record, allow_nan=True)


def _set_ap70(value):
    return lambda record: record["metrics"].__setitem__("ap70", value)


BAD_EDITS = {
    "a word": _set_ap70("high"),
    "no metrics": lambda record: record.pop("metrics"),
    "above 1": _set_ap70(5.0),
    "NaN": _set_ap70(float("nan")),
}


def test_records_that_break_their_schema_are_skipped_counted_and_recomputed(tmp_path, capsys):
    cells = _grid()
    path = tmp_path / "results.jsonl"
    clean = run_sweep(cells, path, workers=1, cell_fn=fake_cell, progress=False)
    lines = path.read_text().splitlines()
    path.write_text("\n".join(_edited(line, edit) for line, edit in
                              zip(lines, BAD_EDITS.values(), strict=True)) + "\n")
    capsys.readouterr()
    CALLS.clear()
    again = run_sweep(cells, path, workers=1, cell_fn=fake_cell, progress=False)
    assert (again.ran, again.skipped, again.unreadable) == (4, 0, 4)
    assert sorted(CALLS) == sorted(c.key for c in cells)
    assert again.records == clean.records  # recomputed, the same numbers
    warning = capsys.readouterr().err
    assert f"{path}: 4 unreadable line(s) skipped" in warning
    assert "line 1: metrics.ap70 expects a number; got 'high'" in warning
    assert "line 2: missing metrics" in warning
    assert "line 3: metrics.ap70=5.0 is out of range; allowed [0.0, 1.0]" in warning
    assert "line 4: metrics.ap70=nan must be finite" in warning
    report = write_report(again.records, tmp_path, with_plots=False).markdown
    assert "255" not in report and "seeds per setting: 2" in report


def _set_cell(name, value):
    return lambda record: record["cell"].__setitem__(name, value)


def test_records_whose_cell_breaks_its_schema_are_skipped_not_fatal(tmp_path, capsys):
    """The cell is part of the schema too: a word for its noise level used to escape the
    check (computing the key raised) and stop the sweep with no file or line."""
    cells = _grid()
    path = tmp_path / "results.jsonl"
    clean = run_sweep(cells, path, workers=1, cell_fn=fake_cell, progress=False)
    edits = [_set_cell("noise", "x"), _set_cell("seed", "0"), _set_cell("steps", 0),
             lambda record: record["cell"].pop("policy")]
    lines = path.read_text().splitlines()
    path.write_text("\n".join(_edited(line, edit) for line, edit in
                              zip(lines, edits, strict=True)) + "\n")
    capsys.readouterr()
    again = run_sweep(cells, path, workers=1, cell_fn=fake_cell, progress=False)
    assert (again.ran, again.unreadable) == (4, 4)
    assert again.records == clean.records
    warning = capsys.readouterr().err
    assert "line 1: cell.noise expects a number; got 'x'" in warning
    assert "line 2: cell.seed expects an integer" in warning
    assert "line 3: cell.steps=0 is out of range" in warning
    assert "line 4: cell without policy" in warning


def test_a_null_metric_is_a_valid_record(tmp_path):
    """NaN (AP of an episode with no ground truth and no prediction) is written as null:
    that record is valid and reused."""
    cells = _grid(seeds=[0])
    path = tmp_path / "results.jsonl"
    run_sweep(cells, path, workers=1, cell_fn=fake_cell, progress=False)
    lines = [_edited(line, _set_ap70(None)) for line in path.read_text().splitlines()]
    path.write_text("\n".join(lines) + "\n")
    again = run_sweep(cells, path, workers=1, cell_fn=fake_cell, progress=False)
    assert (again.ran, again.skipped, again.unreadable) == (0, 2, 0)
    assert all(r["metrics"]["ap70"] is None for r in again.records)


# --- Every file a cell reads is in its provenance (item 2) ------------------------------


def _rerun(cells, path):
    """A second sweep of ``cells`` into ``path`` (a new process would hash afresh too)."""
    CALLS.clear()
    return run_sweep(cells, path, workers=1, cell_fn=fake_cell, progress=False)


def _overwrite(path, data: bytes) -> None:
    """Rewrite ``path`` as retraining would: other bytes, a newer modification time."""
    before = path.stat().st_mtime_ns
    path.write_bytes(data)
    os.utime(path, ns=(before + 10**9, before + 10**9))


def test_overwritten_detector_weights_make_the_records_stale(tmp_path):
    weights = tmp_path / "detector.pt"
    weights.write_bytes(b"first training")
    cells = build_grid(["crowded_intersection"], [0.4], ["identity"], [0], 2,
                       overrides={"detector": "learned", "detector.params.weights": str(weights)})
    path = tmp_path / "results.jsonl"
    run_sweep(cells, path, workers=1, cell_fn=fake_cell, progress=False)
    assert (_rerun(cells, path).ran, CALLS) == (0, [])
    _overwrite(weights, b"retrained!!!!!")  # the same size
    again = _rerun(cells, path)
    assert (again.ran, again.skipped, again.stale) == (1, 0, 1)


def _replay_folder(root, x: float):
    (root / "0").mkdir(parents=True, exist_ok=True)
    (root / "0" / "000068.yaml").write_text(f"lidar_pose: [{x}, 0, 1.9, 0, 0, 0]\n")
    (root / "0" / "000068.pcd").write_bytes(b"points")  # never read by the replay
    return root


def test_an_edited_replay_label_makes_the_records_stale(tmp_path):
    folder = _replay_folder(tmp_path / "scene", x=1.0)
    cells = build_grid(["opv2v_replay"], [0.4], ["identity"], [0], 2,
                       overrides={"traffic.path": str(folder)})
    path = tmp_path / "results.jsonl"
    run_sweep(cells, path, workers=1, cell_fn=fake_cell, progress=False)
    (folder / "0" / "000068.pcd").write_bytes(b"other points")
    assert _rerun(cells, path).ran == 0  # point clouds are not read, not hashed
    _overwrite(folder / "0" / "000068.yaml", b"lidar_pose: [2.0, 0, 1.9, 0, 0, 0]\n")
    assert _rerun(cells, path).stale == 1


class WeightsPolicy:
    """A policy that reads a weights file and says so (the ReadsFiles hook)."""

    def __init__(self, weights: str) -> None:
        self.weights = weights

    def input_files(self) -> list[str]:
        return [self.weights]

    def __call__(self, observation, info=None):
        raise NotImplementedError("never run: the sweep runs fake cells")


def test_the_files_a_policy_declares_are_in_the_provenance(tmp_path, monkeypatch):
    import roco_env.policies as policies

    monkeypatch.setattr(policies, "_REGISTRY", dict(policies._REGISTRY))
    policies.register_policy("with_weights", "test_sweeps_trust:WeightsPolicy")
    weights = tmp_path / "policy.bin"
    weights.write_bytes(b"v1")
    cells = build_grid(["s"], [0.4], [f"with_weights:weights={weights}"], [0], 2)
    path = tmp_path / "results.jsonl"
    run_sweep(cells, path, workers=1, cell_fn=fake_cell, progress=False)
    assert _rerun(cells, path).ran == 0
    _overwrite(weights, b"v2")
    assert _rerun(cells, path).stale == 1


def test_a_file_is_hashed_once_while_its_size_and_mtime_stay(tmp_path, monkeypatch):
    digests = []
    file_digest = hashlib.file_digest

    def counting(handle, name):
        digests.append(handle.name)
        return file_digest(handle, name)

    monkeypatch.setattr(hashlib, "file_digest", counting)
    weights = tmp_path / "w.pt"
    weights.write_bytes(b"weights")
    for _ in range(3):  # three sweeps of one process, each with its own Provenance
        assert len(provenance.content_hashes(weights)) == 64
    assert digests == [str(weights)]
    _overwrite(weights, b"WEIGHTS")
    provenance.content_hashes(weights)
    assert digests == [str(weights)] * 2


def test_a_policy_must_declare_its_files_as_a_list_of_paths():
    from roco_env.policies.base import policy_input_files

    assert policy_input_files(WeightsPolicy("w.bin")) == (Path("w.bin"),)
    assert policy_input_files(lambda observation, info=None: None) == ()
    with pytest.raises(TypeError, match=r"WeightsPolicy.input_files\(\) must return a list "
                       "of paths; got 'w.bin'"):
        policy_input_files(type("WeightsPolicy", (WeightsPolicy,), {
            "input_files": lambda self: self.weights})("w.bin"))


# --- One sweep at a time per output folder (item 4) -------------------------------------

HOLD_LOCK = """
import sys, time
from roco_env.sweeps.store import ResultStore
with ResultStore(sys.argv[1]).exclusive():
    print("locked", flush=True)
    time.sleep(60)
"""


def _holding_process(results) -> subprocess.Popen:
    """A process that holds the results file's lock, as a running sweep does."""
    process = subprocess.Popen([sys.executable, "-c", HOLD_LOCK, str(results)],
                               stdout=subprocess.PIPE, text=True)
    assert process.stdout.readline().strip() == "locked"
    return process


@pytest.mark.skipif(sys.platform == "win32", reason="no fcntl lock on Windows")
def test_a_second_sweep_into_a_busy_folder_stops_and_a_killed_one_leaves_no_lock(tmp_path,
                                                                                 capsys):
    cells = _grid()
    results = tmp_path / "results.jsonl"
    holder = _holding_process(results)
    try:
        with pytest.raises(ResultsInUse, match=f"{results} is being written by another sweep "
                           rf"\(pid {holder.pid}\); wait for it to finish"):
            run_sweep(cells, results, workers=1, cell_fn=fake_cell, progress=False)
        assert CALLS == [] and not results.exists()
        code = main(["compare", "--scenario", "urban_intersection", "--policies", "identity",
                     "--out", str(tmp_path), "--quiet", "--workers", "1"])
        assert code == 2
        assert f"roco-env compare: error: {results} is being written by another sweep" \
            in capsys.readouterr().err
    finally:
        holder.kill()  # SIGKILL: no clean-up runs
        holder.wait()
    outcome = run_sweep(cells, results, workers=1, cell_fn=fake_cell, progress=False)
    assert (outcome.ran, len(ResultStore(results).records())) == (4, 4)  # each cell once


# --- Workers die with a killed sweep (item 5) -------------------------------------------


@pytest.mark.slow  # a real compare with a pool: 7-25 s
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="watches a pidfd: Linux")
def test_sigkill_of_compare_leaves_no_fork_server_worker_or_resource_tracker(tmp_path):
    command = [str(Path(sys.executable).with_name("roco-env")), "compare", "--scenario",
               "urban_roundabout", "--policies", "identity", "--noise", "0", "0.4", "--seeds",
               "4", "--steps", "10", "--workers", "2", "--quiet", "--no-plots", "--out",
               str(tmp_path), "--set", "cavs=2", "--set", "rsus=0"]
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    descendants: set[int] = set()
    try:
        deadline = time.monotonic() + 60
        workers: set[int] = set()
        while time.monotonic() < deadline and process.poll() is None and len(workers) < 2:
            # fork server and resource tracker: children of the sweep; workers: the server's
            helpers = _children(process.pid)
            workers = {pid for helper in helpers for pid in _children(helper)}
            descendants |= helpers | workers
            time.sleep(0.05)
        assert len(workers) == 2, "the sweep ended before its pool started"
        process.kill()  # SIGKILL to the sweep alone: no handler, no clean-up runs
        process.wait()
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and any(_alive(pid) for pid in descendants):
            time.sleep(0.05)
        survivors = [pid for pid in descendants if _alive(pid)]
    finally:
        for pid in descendants:  # leave nothing behind even when the check fails
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)
    assert not survivors, "processes outlived the killed sweep"


# --- The time per call is a warm one (item 7) -------------------------------------------


class FakeClock:
    """perf_counter stand-in: time moves only when a policy call says how long it took."""

    def __init__(self) -> None:
        self.now = 0.0

    def perf_counter(self) -> float:
        return self.now


def test_time_per_call_leaves_out_each_agents_first_call(monkeypatch):
    """The first call of each policy pays numba's compilation (hundreds of ms in a fresh
    worker): it must not be in the reported per-call time."""
    from roco_env import rollout
    from roco_env.sweeps import episode

    clock = FakeClock()
    monkeypatch.setattr(rollout, "time", clock)  # the episode loop times each call

    class Compiling:
        calls = 0

        def __call__(self, observation, info=None):
            clock.now += 0.5 if self.calls == 0 else 0.002  # s: compiled once, then warm
            self.calls += 1
            return np.zeros((len(observation["collab_mask"]), 3), dtype=np.float32)

    scorers = []
    cell = Cell("crowded_intersection", 0.0, "identity", 0, 3, overrides=(("cavs", 2), ("rsus", 0)))
    episode.run_episode(cell, policy_factory=Compiling, on_scorer=scorers.append)
    assert scorers[0].time_per_call_ms() == pytest.approx(2.0)  # not (2 x 500 + 4 x 2) / 6


def test_a_wrapped_policy_still_declares_its_files(tmp_path, monkeypatch):
    """Temporal smoothing around a policy that reads weights: the sweep must still hash
    them, or retraining the inner policy would leave its records reused."""
    import roco_env.policies as policies
    from roco_env.policies.base import policy_input_files
    from roco_env.policies.temporal import TemporalSmoothing

    assert policy_input_files(TemporalSmoothing(WeightsPolicy("w.bin"))) == (Path("w.bin"),)
    assert policy_input_files(TemporalSmoothing("identity")) == ()
    monkeypatch.setattr(policies, "_REGISTRY", dict(policies._REGISTRY))
    policies.register_policy("with_weights", "test_sweeps_trust:WeightsPolicy")
    weights = tmp_path / "policy.bin"
    weights.write_bytes(b"v1")
    spec = f"roco_env.policies.temporal:TemporalSmoothing:policy=with_weights,weights={weights}"
    cells = build_grid(["s"], [0.4], [spec], [0], 2)
    path = tmp_path / "results.jsonl"
    run_sweep(cells, path, workers=1, cell_fn=fake_cell, progress=False)
    assert _rerun(cells, path).ran == 0
    _overwrite(weights, b"v2")
    assert _rerun(cells, path).stale == 1
