"""Baseline experiments: valid grids, printed commands equal to the runner and to the ones
baselines/README.md quotes, a smoke run."""

from __future__ import annotations

import shlex
from pathlib import Path

import pytest

from roco_env.cli import build_parser
from roco_env.cli.compare import grid_from_args
from roco_env.sweeps.baselines import EXPERIMENTS, experiment, main
from roco_env.sweeps.cells import validate_grid


@pytest.mark.parametrize("item", EXPERIMENTS, ids=lambda e: e.name)
def test_printed_command_builds_the_same_grid(item):
    words = shlex.split(item.command("baselines/results"))
    assert words[:2] == ["roco-env", "compare"]
    args = build_parser().parse_args(words[1:])
    assert [c.key for c in grid_from_args(args)] == [c.key for c in item.cells()]
    validate_grid(item.cells(smoke=True))  # scenarios, overrides and policy specs all valid


def test_the_readme_quotes_every_experiments_command():
    """baselines/README.md quotes the very commands the runner prints, and no others."""
    readme = (Path(__file__).resolve().parents[1] / "baselines" / "README.md").read_text()
    quoted = {line.strip() for line in readme.splitlines()
              if line.startswith("    roco-env compare ")}
    assert quoted == {item.command("baselines/results") for item in EXPERIMENTS}


def test_ablations_cover_the_papers_tables():
    # tau2 alone: the fallback gate, which widens a too-small tau2, is off
    assert experiment("ablation_tau2").policies[:4] == tuple(
        f"roco:coarse_tau2=null,tau2={t}" for t in (1, 2, 3, 4))
    assert set(experiment("ablation_similarity").policies) >= {
        "roco:use_edge_similarity=false", "roco:use_distance_similarity=false"}
    assert "roco:robust_kernel=null" in experiment("ablation_modules").policies
    assert experiment("paper_protocol").noises == (0.0, 0.2, 0.4, 0.6, 0.8)
    assert experiment("beyond_paper").noises == (1.0, 1.5, 2.0)
    large = experiment("large_noise")
    assert large.noises == (0.0, 1.0, 2.0, 3.0, 5.0, 10.0)
    assert {"ransac", "v2i_calib", "freealign", "roco_fallback", "oracle"} <= set(large.policies)
    with pytest.raises(ValueError, match="unknown experiment 'nope'; available: paper_protocol"):
        experiment("nope")


def test_smoke_run_writes_reports(tmp_path, capsys):
    assert main(["--smoke", "--only", "ablation_modules", "--out", str(tmp_path), "--quiet",
                 "--workers", "1"]) == 0
    report = (tmp_path / "ablation_modules" / "report.md").read_text()
    assert "| roco:robust_kernel=null |" in report
    assert main(["--only", "nope"]) == 2
    assert "unknown experiment" in capsys.readouterr().err


def test_antialias_ablation_switches_every_component_off():
    from dataclasses import fields

    from roco_env.policies.antialias import AntiAliasParams
    from roco_env.policies.roco import RoCoParams

    own = {f.name for f in fields(AntiAliasParams)} - {f.name for f in fields(RoCoParams)}
    switches = {name for name in own if name.startswith("use_")}
    assert len(switches) == 6
    policies = set(experiment("ablation_antialias").policies)
    assert {f"roco_antialias:{s}=false" for s in switches} | {"roco", "roco_antialias"} == policies
