"""Results store, resume and failure handling of the sweep, with an injected cell function.

The real-env versions (subprocess kill, Ray) are in test_sweeps_sweep.py.
"""

from __future__ import annotations

import json
import sys

import pytest
from conftest import CALLS, FAILING_NOISE, fake_cell

import roco_env
from roco_env.sweeps import provenance
from roco_env.sweeps.cells import build_grid
from roco_env.sweeps.records import WALL_TIME_FIELDS, error_record, ok_record
from roco_env.sweeps.store import ResultStore
from roco_env.sweeps.sweep import run_sweep, stored_results


@pytest.fixture(autouse=True)
def _reset_fake():
    CALLS.clear()
    FAILING_NOISE.clear()


def _grid():
    return build_grid(["s"], noises=[0.0, 0.4, 0.8], policies=["identity", "roco"],
                      seeds=[0, 1], steps=2)


def _record(index: int, ap70: float) -> dict:
    """A valid ok record of the grid's cell ``index`` with AP@0.7 ``ap70``."""
    cell = _grid()[index]
    return ok_record(cell, {"ap30": 1.0, "ap50": 1.0, "ap70": ap70},
                     {"before": [], "after": []}, 0.1)


def test_store_is_strict_jsonl_and_last_record_wins(tmp_path):
    a, b = _grid()[:2]
    store = ResultStore(tmp_path / "r.jsonl")
    store.append(error_record(a, RuntimeError("x"), 0.1))
    store.append(_record(1, float("nan")))
    store.append(_record(0, 0.5))
    lines = (tmp_path / "r.jsonl").read_text().splitlines()
    assert len(lines) == 3
    assert json.loads(lines[1])["metrics"]["ap70"] is None  # NaN stored as null
    assert store.completed_keys() == {a.key, b.key}
    assert store.latest()[a.key]["metrics"]["ap70"] == 0.5
    assert [r["key"] for r in store.select([b.key, "zz", a.key])] == [b.key, a.key]


def test_torn_last_line_is_skipped_and_sealed(tmp_path):
    path = tmp_path / "r.jsonl"
    store = ResultStore(path)
    store.append(_record(0, 0.5))
    with path.open("a") as handle:
        handle.write('{"key": "b", "sta')  # a kill in the middle of a write
    assert store.completed_keys() == {_grid()[0].key}
    assert store.skipped == [(2, "not JSON (Unterminated string starting at)")]
    store.append(_record(2, 0.5))
    assert store.completed_keys() == {_grid()[0].key, _grid()[2].key}
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


def test_unreadable_lines_are_counted_and_reported(tmp_path, capsys):
    cells = _grid()[:3]
    path = tmp_path / "results.jsonl"
    run_sweep(cells, path, workers=1, cell_fn=fake_cell, progress=False)
    with path.open("a") as handle:
        handle.write("not json\n[1, 2]\n{\"key\": \"x\"}\n\n")
    outcome = run_sweep(cells, path, workers=1, cell_fn=fake_cell, progress=False)
    assert outcome.unreadable == 3 and outcome.skipped == 3
    assert "3 unreadable line(s) skipped" in capsys.readouterr().err


def _yaml_scenario(path, cavs):
    path.write_text(f"agents:\n  cavs: {cavs}\n  rsus: 0\n")
    return str(path)


def test_a_record_of_other_scenario_content_is_recomputed(tmp_path, capsys):
    """Editing the scenario YAML in place (same path, same key) makes the record stale."""
    scenario = _yaml_scenario(tmp_path / "my.yaml", cavs=2)
    cells = build_grid([scenario], [0.4], ["identity"], [0], 2)
    path = tmp_path / "results.jsonl"
    run_sweep(cells, path, workers=1, cell_fn=fake_cell, progress=False)
    CALLS.clear()
    again = run_sweep(cells, path, workers=1, cell_fn=fake_cell, progress=False)
    assert (again.ran, again.skipped, again.stale) == (0, 1, 0) and CALLS == []
    _yaml_scenario(tmp_path / "my.yaml", cavs=3)
    edited = run_sweep(cells, path, workers=1, cell_fn=fake_cell, progress=False)
    assert (edited.ran, edited.skipped, edited.stale) == (1, 0, 1) and CALLS == [cells[0].key]
    assert "1 cell(s) recomputed" in capsys.readouterr().err


def test_a_record_of_other_code_is_recomputed(tmp_path, monkeypatch):
    cells = _grid()[:2]
    path = tmp_path / "results.jsonl"
    run_sweep(cells, path, workers=1, cell_fn=fake_cell, progress=False)
    monkeypatch.setattr(provenance, "source_hash", lambda: "edited source")
    assert run_sweep(cells, path, workers=1, cell_fn=fake_cell, progress=False).stale == 2
    monkeypatch.setattr(roco_env, "__version__", "9.9")
    outcome = run_sweep(cells, path, workers=1, cell_fn=fake_cell, progress=False)
    assert (outcome.ran, outcome.stale) == (2, 2)
    assert stored_results(path).stale == 0  # the latest records are current again
    monkeypatch.undo()
    assert stored_results(path).stale == 2  # ... for the code that wrote them only


def test_source_hash_covers_the_package_files():
    assert len(provenance.source_hash()) == 64
    assert provenance.Provenance().of(_grid()[0]) == provenance.Provenance().of(_grid()[0])
    assert provenance.Provenance().of(_grid()[0]) != provenance.Provenance().of(_grid()[1])
