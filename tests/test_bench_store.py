"""Results store, resume and failure handling of the sweep, with an injected cell function.

The real-env versions (subprocess kill, Ray) are in test_bench_sweep.py.
"""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

from roco_env.bench.grid import Cell, build_grid
from roco_env.bench.records import WALL_TIME_FIELDS, ok_record
from roco_env.bench.store import ResultStore
from roco_env.bench.sweep import run_sweep

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


@pytest.fixture(autouse=True)
def _reset_fake():
    CALLS.clear()
    FAILING_NOISE.clear()


def _grid():
    return build_grid(["s"], noises=[0.0, 0.4, 0.8], policies=["identity", "roco"],
                      seeds=[0, 1], steps=2)


def test_store_is_strict_jsonl_and_last_record_wins(tmp_path):
    store = ResultStore(tmp_path / "r.jsonl")
    store.append({"key": "a", "status": "error", "error": "x"})
    store.append({"key": "b", "status": "ok", "metrics": {"ap70": float("nan")}})
    store.append({"key": "a", "status": "ok", "metrics": {"ap70": 0.5}})
    lines = (tmp_path / "r.jsonl").read_text().splitlines()
    assert len(lines) == 3
    assert json.loads(lines[1])["metrics"]["ap70"] is None  # NaN stored as null
    assert store.completed_keys() == {"a", "b"}
    assert store.latest()["a"]["metrics"]["ap70"] == 0.5
    assert [r["key"] for r in store.select(["b", "zz", "a"])] == ["b", "a"]


def test_torn_last_line_is_skipped_and_sealed(tmp_path):
    path = tmp_path / "r.jsonl"
    store = ResultStore(path)
    store.append({"key": "a", "status": "ok"})
    with path.open("a") as handle:
        handle.write('{"key": "b", "sta')  # a kill in the middle of a write
    assert store.completed_keys() == {"a"}
    store.append({"key": "c", "status": "ok"})
    assert store.completed_keys() == {"a", "c"}
    assert len(path.read_text().splitlines()) == 3


def test_resume_skips_finished_cells(tmp_path):
    cells = _grid()
    path = tmp_path / "results.jsonl"
    first = run_sweep(cells[:5], path, workers=1, cell_fn=fake_cell, progress=False)
    assert (first.ran, first.skipped) == (5, 0)
    CALLS.clear()
    second = run_sweep(cells, path, workers=1, cell_fn=fake_cell, progress=False)
    assert (second.ran, second.skipped) == (len(cells) - 5, 5)
    assert sorted(CALLS) == sorted(c.key for c in cells[5:])
    assert [r["key"] for r in second.records] == [c.key for c in cells]
    keys = [json.loads(line)["key"] for line in path.read_text().splitlines()]
    assert len(keys) == len(set(keys)) == len(cells)


def test_failing_cell_is_recorded_the_rest_finish_and_it_is_retried(tmp_path):
    cells = _grid()
    path = tmp_path / "results.jsonl"
    FAILING_NOISE.add(0.4)
    outcome = run_sweep(cells, path, workers=1, cell_fn=fake_cell, progress=False)
    failed = [r for r in outcome.records if r["status"] == "error"]
    assert outcome.failed == len(failed) == 4
    assert all("RuntimeError: boom at noise 0.4" in r["error"] for r in failed)
    assert all("fake_cell" in r["traceback"] for r in failed)
    assert sum(r["status"] == "ok" for r in outcome.records) == len(cells) - 4
    FAILING_NOISE.clear()
    CALLS.clear()
    retry = run_sweep(cells, path, workers=1, cell_fn=fake_cell, progress=False)
    assert retry.ran == 4 and retry.failed == 0
    assert sorted(CALLS) == sorted(r["key"] for r in failed)
    assert all(r["status"] == "ok" for r in retry.records)


def test_process_pool_matches_serial(tmp_path):
    cells = _grid()
    serial = run_sweep(cells, tmp_path / "a.jsonl", workers=1, cell_fn=fake_cell, progress=False)
    pooled = run_sweep(cells, tmp_path / "b.jsonl", workers=2, cell_fn=fake_cell, progress=False)

    def strip(records):
        return [{k: v for k, v in r.items() if k not in WALL_TIME_FIELDS} for r in records]

    assert strip(serial.records) == strip(pooled.records)


def test_unknown_backend_and_bad_workers(tmp_path):
    with pytest.raises(ValueError, match="unknown backend 'dask'; choose one of: local, ray"):
        run_sweep(_grid(), tmp_path / "r.jsonl", backend="dask", cell_fn=fake_cell)
    with pytest.raises(ValueError, match="workers must be >= 1"):
        run_sweep(_grid(), tmp_path / "r.jsonl", workers=0, cell_fn=fake_cell)


def test_ray_backend_without_ray_says_how_to_install(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # makes `import ray` fail
    with pytest.raises(ValueError, match=r"pip install roco-env\[ray\]"):
        run_sweep(_grid(), tmp_path / "r.jsonl", backend="ray", cell_fn=fake_cell)
