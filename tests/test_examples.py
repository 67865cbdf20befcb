"""Every script in examples/ runs to completion in quick mode (ROCO_EXAMPLE_QUICK=1)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
EXPECTED = {  # a line fragment each example must print
    "quickstart.py": "AP@0.7 =",
    "compare_policies.py": "### AP@0.7 (%)",
    "custom_policy.py": "nn-icp (this file)",
    "stress_crowding.py": "nearest-neighbour gap",
    "rllib_ppo.py": "",  # prints a skip notice without ray[rllib], training output with it
}


def test_every_example_is_covered():
    assert sorted(p.name for p in EXAMPLES.glob("*.py")) == sorted(EXPECTED)


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_example_runs_quick(name, tmp_path):
    env = {**os.environ, "ROCO_EXAMPLE_QUICK": "1", "MPLBACKEND": "Agg"}
    done = subprocess.run([sys.executable, str(EXAMPLES / name)], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=180)
    assert done.returncode == 0, done.stderr[-3000:]
    assert EXPECTED[name] in done.stdout
