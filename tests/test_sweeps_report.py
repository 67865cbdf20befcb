"""Report files (Markdown tables, CSV, PNG plots) are written and parse back to the numbers."""

from __future__ import annotations

import csv

import numpy as np
from conftest import FAILING_NOISE, fake_cell
from PIL import Image

from roco_env.sweeps.cells import build_grid
from roco_env.sweeps.sweep import run_sweep
from roco_env.sweeps.sweep_report import write_report


def _markdown_tables(text: str) -> dict[str, list[list[str]]]:
    """Heading -> table rows (cells stripped), for every table under a ### heading."""
    tables, heading = {}, None
    for line in text.splitlines():
        if line.startswith("#"):
            heading = line.lstrip("# ").strip()
        elif line.startswith("|") and not line.startswith("|---"):
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            tables.setdefault(heading, []).append(cells)
    return tables


def test_report_files_parse_back(tmp_path):
    cells = build_grid(["s"], noises=[0.0, 0.4, 1.5], policies=["identity", "roco"],
                       seeds=[0, 1], steps=2, densities=[1.0, 2.0])
    FAILING_NOISE.add(1.5)
    try:
        outcome = run_sweep(cells, tmp_path / "results.jsonl", workers=1, cell_fn=fake_cell,
                            progress=False)
    finally:
        FAILING_NOISE.clear()
    report = write_report(outcome.records, tmp_path / "out")
    names = sorted(p.name for p in report.files)
    assert names == ["ap70_vs_density.png", "ap70_vs_noise.png", "report.md",
                     "rpe_distribution.png", "summary.csv"]
    for path in report.files:
        if path.suffix == ".png":
            with Image.open(path) as image:
                assert image.size[0] > 300 and image.size[1] > 200

    text = (tmp_path / "out" / "report.md").read_text()
    assert text == report.markdown
    tables = _markdown_tables(text)
    ap70 = tables["AP@0.7 (%)"]
    header = ap70[0]
    assert header[1:] == ["0.0/0.0", "0.4/0.4", "1.5/1.5"]
    rows = {r[0]: r[1:] for r in ap70[1:3]}  # first scenario/density section
    # fake AP@0.7 = 0.7 - noise/2 + 0.01*seed, mean over seeds 0, 1 -> +0.005
    assert rows["identity"][:2] == [f"{100 * 0.705:.1f}", f"{100 * 0.505:.1f}"]
    assert rows["roco"][2] == "err"
    assert "## Failed cells" in text and "boom at noise 1.5" in text
    assert "AP@0.7 (%) vs density" in tables

    with (tmp_path / "out" / "summary.csv").open() as handle:
        summary = list(csv.DictReader(handle))
    assert len(summary) == 2 * 3 * 2  # densities x noises x policies
    good = [r for r in summary if r["noise"] == "0.4"]
    assert all(int(r["seeds"]) == 2 and int(r["failed"]) == 0 for r in good)
    assert np.isclose(float(good[0]["ap70"]), 0.505)
    # pooled RPE after correction is the fake's "before / 10"
    assert np.isclose(float(good[0]["rpe_t_median"]), float(good[0]["rpe_t_median_before"]) / 10)
    bad = [r for r in summary if r["noise"] == "1.5"]
    assert all(int(r["seeds"]) == 0 and int(r["failed"]) == 2 for r in bad)


def test_a_grid_axis_gets_its_tables_and_plot(tmp_path):
    cells = build_grid(["s"], noises=[0.0, 0.4], policies=["identity", "roco"], seeds=[0],
                       steps=2, overrides={"comm.delay": "fixed"},
                       axes={"comm.delay_params.delay_ms": (0, 100, 1000),
                             "comm.loss": ("none", "bernoulli")})
    outcome = run_sweep(cells, tmp_path / "results.jsonl", workers=1, cell_fn=fake_cell,
                        progress=False)
    report = write_report(outcome.records, tmp_path / "out")
    names = sorted(p.name for p in report.files)
    assert "ap70_vs_comm_delay_params_delay_ms.png" in names
    assert "ap70_vs_comm_loss.png" in names
    tables = _markdown_tables(report.markdown)
    block = tables["AP@0.7 (%) vs comm.delay_params.delay_ms (noise 0.4/0.4, comm.loss=none)"]
    assert block[0] == ["Policy \\ comm.delay_params.delay_ms", "0", "100", "1000"]
    assert block[1][0] == "identity" and block[1][1:] == [f"{100 * 0.5:.1f}"] * 3
    assert tables["AP@0.5 (%) vs comm.loss (noise 0.0/0.0, comm.delay_params.delay_ms=100)"][0] \
        == ["Policy \\ comm.loss", "bernoulli", "none"]
    assert "## s (density default; comm.delay=fixed)" in report.markdown
    pose = tables["Relative pose error and success"]
    assert pose[0][:4] == ["Policy", "Noise", "comm.delay_params.delay_ms", "comm.loss"]
    assert "Worse by > 0.5 m (%)" in pose[0]
    assert len(pose) == 1 + 2 * 2 * 3 * 2
    with (tmp_path / "out" / "summary.csv").open() as handle:
        summary = list(csv.DictReader(handle))
    assert {r["comm.delay_params.delay_ms"] for r in summary} == {"0", "100", "1000"}
