"""Sweeps on the real env (tiny settings): resume after a kill, failing cells, Ray == local."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from roco_env.sweeps.backends import run_local
from roco_env.sweeps.cells import Cell, build_grid
from roco_env.sweeps.records import WALL_TIME_FIELDS
from roco_env.sweeps.store import ResultStore
from roco_env.sweeps.sweep import run_sweep

TINY = {"cavs": 2, "rsus": 1}  # few agents: fast cells
SCENARIO = "crowded_intersection"


def _strip(records: list[dict]) -> list[dict]:
    """Records without the wall times (the only fields allowed to differ between runs)."""
    return sorted(({k: v for k, v in r.items() if k not in WALL_TIME_FIELDS} for r in records),
                  key=lambda r: r["key"])


def _lines(path: Path) -> list[dict]:
    """Every record in the file (a line torn by the kill, if any, is not a record)."""
    return ResultStore(path).records()


def test_resume_after_kill_gives_the_uninterrupted_results(tmp_path):
    out = tmp_path / "killed"
    command = [str(Path(sys.executable).with_name("roco-env")), "compare", "--scenario", SCENARIO,
               "--policies", "identity", "oracle", "--noise", "0", "0.4", "0.8", "--seeds", "2",
               "--steps", "4", "--workers", "1", "--quiet", "--no-plots", "--out", str(out),
               "--set", "cavs=2", "--set", "rsus=1"]
    results = out / "results.jsonl"
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                               start_new_session=True)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and process.poll() is None:
        if results.exists() and results.read_text().count("\n") >= 1:
            break
        time.sleep(0.02)
    assert process.poll() is None, process.stderr.read().decode()
    os.killpg(process.pid, signal.SIGKILL)  # the sweep and anything it started
    process.wait()
    written = len(_lines(results))
    assert 1 <= written < 12, f"kill came too late or too early: {written} cells written"

    finished = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert finished.returncode == 0, finished.stderr
    assert f"{12 - written} run, {written} resumed" in finished.stdout
    resumed = _lines(results)
    assert len(resumed) == 12 and len({r["key"] for r in resumed}) == 12  # no duplicates

    cells = build_grid([SCENARIO], [0.0, 0.4, 0.8], ["identity", "oracle"], [0, 1], 4,
                       overrides=TINY)
    reference = run_sweep(cells, tmp_path / "reference" / "results.jsonl", workers=1,
                          progress=False)
    assert _strip(resumed) == _strip(reference.records)
    assert all(r["status"] == "ok" for r in resumed)


def test_failing_cells_are_recorded_and_the_rest_finish(tmp_path):
    good = build_grid([SCENARIO], [0.4], ["identity"], [0, 1], 2, overrides=TINY)
    bad_override = Cell(SCENARIO, 50.0, "identity", 0, 2, overrides=tuple(TINY.items()))
    bad_policy = Cell(SCENARIO, 0.4, "oracle:no_such_param=1", 0, 2,
                      overrides=tuple(TINY.items()))
    outcome = run_sweep([good[0], bad_override, bad_policy, good[1]], tmp_path / "r.jsonl",
                        workers=2, progress=False)
    status = {r["key"]: r for r in outcome.records}
    assert outcome.failed == 2
    assert status[bad_override.key]["status"] == "error"
    assert "sigma_t" in status[bad_override.key]["error"]
    assert "Traceback" in status[bad_override.key]["traceback"]
    assert status[bad_policy.key]["status"] == "error"
    assert status[bad_policy.key]["error"].startswith("ValueError: policy 'oracle' takes no ")
    assert all(status[c.key]["status"] == "ok" for c in good)
    assert all(status[c.key]["metrics"]["frames"] > 0 for c in good)


def _torch_threads(cell: Cell) -> dict:
    return {"threads": torch.get_num_threads()}


def _pid(cell: Cell) -> dict:
    time.sleep(0.2)  # long enough for both workers to take cells
    return {"pid": os.getpid()}


def test_a_process_keeps_its_pool_for_later_sweeps_and_drops_a_stopped_ones():
    """Later sweeps run on the same (warm) workers; a sweep stopped early kills its
    workers, and the next one starts new ones."""
    cells = build_grid([SCENARIO], [0.4], ["identity"], [0, 1, 2, 3], 2)
    first = {r["pid"] for _, r in run_local(cells, _pid, workers=2)}
    assert {r["pid"] for _, r in run_local(cells, _pid, workers=2)} <= first
    stopped = run_local(cells, _pid, workers=2)
    next(stopped)
    stopped.close()  # the consumer is gone
    assert all(not _alive(pid) for pid in first)
    assert not {r["pid"] for _, r in run_local(cells, _pid, workers=2)} & first


def test_cells_run_in_this_process_get_one_torch_thread_as_the_pool_workers_do():
    """The learned detector's default threads follow torch's count, and its network rounds
    differently on another thread count: workers=1 must not give other records."""
    cells = build_grid([SCENARIO], [0.4], ["identity"], [0, 1], 2)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        for workers in (1, 2):
            records = [r for _, r in run_local(cells, _torch_threads, workers=workers)]
            assert [r["threads"] for r in records] == [1, 1], workers
            assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


HANG_SCRIPT = """
import torch
from roco_env.sweeps.backends import run_local
from roco_env.sweeps.cells import Cell

def cell_fn(cell):
    torch.set_num_threads(2)
    return {"sum": float((torch.rand(1_000_000) * 2.0).sin().sum())}

if __name__ == "__main__":
    torch.set_num_threads(2)
    (torch.rand(1_000_000) * 2.0).sin().sum()  # the parent runs torch on two threads
    cells = [Cell("urban_intersection", 0.0, "identity", s, 1) for s in range(2)]
    print(len([r for _, r in run_local(cells, cell_fn, workers=2)]))
"""


def test_pool_workers_may_use_torch_threads_after_the_parent_did(tmp_path):
    """Local workers do not inherit the parent's OpenMP state: a worker forked from a
    parent that ran torch on two threads hung on its first two-thread operation (the
    pool now starts its workers from a fork server)."""
    script = tmp_path / "threads_after_parent.py"
    script.write_text(HANG_SCRIPT)
    try:
        done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                              timeout=120)
    except subprocess.TimeoutExpired:
        pytest.fail("a pool worker hung in torch's threads")
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "2"


# Ray's own workers run in test_ray_and_local_backends_give_identical_records by default;
# this Ray case with the slow tests (ROCO_SLOW=1).
@pytest.mark.parametrize("backend", ["local", pytest.param("ray", marks=pytest.mark.slow)])
def test_workers_know_the_policies_registered_in_the_sweeps_process(tmp_path, monkeypatch,
                                                                    backend):
    """Local workers start from a fork server and Ray's are its own processes, not copies
    of this one: the registry is handed to them."""
    if backend == "ray":
        pytest.importorskip("ray")
    import roco_env.policies as policies

    monkeypatch.setattr(policies, "_REGISTRY", dict(policies._REGISTRY))
    policies.register_policy("registered_here", "roco_env.policies.basic:IdentityPolicy")
    cells = build_grid([SCENARIO], [0.4], ["registered_here"], [0, 1], 2, overrides=TINY)
    outcome = run_sweep(cells, tmp_path / "r.jsonl", backend=backend, workers=2,
                        progress=False)
    assert [r["status"] for r in outcome.records] == ["ok", "ok"], outcome.records


def test_without_a_fork_server_the_pool_spawns_its_workers(tmp_path, monkeypatch):
    """Windows has no fork server: the workers start as fresh interpreters there, with the
    same records."""
    import multiprocessing

    cells = build_grid([SCENARIO], [0.4], ["identity"], [0, 1], 2, overrides=TINY)
    served = run_sweep(cells, tmp_path / "served.jsonl", workers=2, progress=False)
    asked: list[str] = []
    get_context = multiprocessing.get_context

    def recording(method=None):
        asked.append(method)
        return get_context(method)

    monkeypatch.setattr(multiprocessing, "get_all_start_methods", lambda: ["spawn"])
    monkeypatch.setattr(multiprocessing, "get_context", recording)
    spawned = run_sweep(cells, tmp_path / "spawned.jsonl", workers=2, progress=False)
    assert asked == ["spawn"]
    assert all(r["status"] == "ok" for r in spawned.records)
    assert _strip(spawned.records) == _strip(served.records)


def test_ray_and_local_backends_give_identical_records(tmp_path):
    pytest.importorskip("ray")
    cells = build_grid([SCENARIO], [0.4], ["identity", "oracle"], [0, 1], 2, overrides=TINY)
    local = run_sweep(cells, tmp_path / "local.jsonl", backend="local", workers=2,
                      progress=False)
    # no address: the backend starts (and stops) a local 2-CPU Ray without dashboard
    remote = run_sweep(cells, tmp_path / "ray.jsonl", backend="ray", workers=2, progress=False)
    assert all(r["status"] == "ok" for r in local.records)
    assert _strip(local.records) == _strip(remote.records)


def _children(pid: int) -> set[int]:
    """Pids of the live processes whose parent is ``pid`` (from /proc)."""
    found = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if int(fields[1]) == pid and fields[0] != "Z":
            found.add(int(stat.parent.name))
    return found


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _stoppable_sweep(out: Path) -> list[str]:
    """A `roco-env compare` of 8 cells of 10 steps on 2 workers: it must still run when the
    signal comes (with fewer, a quiet machine finished it first, and the restored default
    handler ended the process)."""
    return [str(Path(sys.executable).with_name("roco-env")), "compare", "--scenario",
            "urban_roundabout", "--policies", "identity", "--noise", "0", "0.4", "--seeds", "4",
            "--steps", "10", "--workers", "2", "--quiet", "--no-plots", "--out", str(out),
            "--set", "cavs=2", "--set", "rsus=0"]


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads the process table from /proc")
# SIGINT's handler also runs by default in the Ctrl-C test below; this SIGINT case with the
# slow tests (ROCO_SLOW=1).
@pytest.mark.parametrize("sig", [signal.SIGTERM,
                                 pytest.param(signal.SIGINT, marks=pytest.mark.slow)])
def test_signal_stops_the_workers_with_one_line_and_the_rerun_resumes(tmp_path, sig):
    out = tmp_path / "stopped"
    command = _stoppable_sweep(out)
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                               text=True)
    try:
        # a bound on the wait, not a speed check: a loaded 2-core machine needs over a
        # minute to import the command and start its pool
        deadline = time.monotonic() + 180
        workers: set[int] = set()
        helpers: set[int] = set()
        while time.monotonic() < deadline and process.poll() is None and len(workers) < 2:
            # the pool's workers are the children of its fork server, a child of the sweep
            helpers = _children(process.pid)
            workers = {pid for helper in helpers for pid in _children(helper)}
            time.sleep(0.05)
        assert len(workers) == 2, process.stderr.read() if process.poll() is not None else ""
        process.send_signal(sig)  # the parent only, as `kill <pid>` does
        _, stderr = process.communicate(timeout=30)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 128 + sig, stderr
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and f"stopped by {sig.name}" in lines[0], stderr
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and any(_alive(w) for w in workers | helpers):
        time.sleep(0.05)
    orphans = [w for w in workers | helpers if _alive(w)]
    for pid in orphans:  # leave nothing behind even when the check fails
        os.kill(pid, signal.SIGKILL)
    assert not orphans, "pool workers or their fork server outlived the sweep"
    written = len(_lines(out / "results.jsonl"))
    finished = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert finished.returncode == 0, finished.stderr
    assert f"{8 - written} run, {written} resumed" in finished.stdout


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads the process table from /proc")
def test_ctrl_c_while_the_fork_server_starts_stops_the_sweep_with_one_line(tmp_path):
    """Ctrl-C reaches the whole process group, the pool's fork server too: one still
    importing torch and the cell's module must ignore it, as the workers do, rather than
    print a KeyboardInterrupt traceback."""
    process = subprocess.Popen(_stoppable_sweep(tmp_path / "stopped"),
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                               start_new_session=True)
    try:
        deadline = time.monotonic() + 180  # a bound on the wait (see above), not a speed check
        while time.monotonic() < deadline and process.poll() is None \
                and not _children(process.pid):
            time.sleep(0.01)
        time.sleep(0.3)  # the fork server has started and is importing (seconds)
        os.killpg(process.pid, signal.SIGINT)
        _, stderr = process.communicate(timeout=30)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "stopped by SIGINT" in lines[0], stderr
