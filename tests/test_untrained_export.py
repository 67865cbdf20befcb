"""baselines/learned_select/untrained.py: the shipped run's command is read back whole."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "baselines" / "learned_select"))

from untrained import run_command  # noqa: E402

from roco_env.training.rl.config import FLAGS  # noqa: E402


def test_the_shipped_run_command_parses_to_its_guard() -> None:
    parser = argparse.ArgumentParser()
    FLAGS.add_to(parser)
    argv = run_command(ROOT / "baselines" / "learned_select" / "fallback" / "report.md")
    config = FLAGS.parse(parser.parse_args(argv))
    assert not any(arg.startswith("--out") for arg in argv)
    assert (config.guard, config.guard_prefer, config.guard_prefer_within_m) == (
        "keep_tested", "roco_fallback", 0.5)
    assert config.total_timesteps == 4480 and config.seed == 0


def test_a_report_without_a_command_is_refused_naming_it(tmp_path: Path) -> None:
    report = tmp_path / "report.md"
    report.write_text("# no command here\n")
    with pytest.raises(ValueError, match="report.md holds no"):
        run_command(report)
