"""Sweep results you can trust (issue 27): bad records are skipped and recomputed, every
file a cell reads is in its provenance, one sweep per output folder, workers die with a
killed sweep, and the time per call is a warm one."""

from __future__ import annotations

import json

import pytest
from conftest import CALLS, FAILING_NOISE, fake_cell

from roco_env.sweeps.grid import build_grid
from roco_env.sweeps.report import write_report
from roco_env.sweeps.sweep import run_sweep


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
