"""Every script in examples/ runs to completion in quick mode (ROCO_EXAMPLE_QUICK=1)."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
# RLlib is a dev extra: with it the example trains one PPO iteration, without it the
# example says it is skipping (and why).
RLLIB = importlib.util.find_spec("ray") is not None and \
    importlib.util.find_spec("ray.rllib") is not None
SB3 = importlib.util.find_spec("stable_baselines3") is not None
EXPECTED = {  # a line fragment each example must print
    "quickstart.py": "AP@0.7 =",
    "compare_policies.py": "### AP@0.7 (%)",
    "custom_policy.py": "nn-icp (this file)",
    "custom_stage.py": "rain 30%, discounted fusion",
    "stress_crowding.py": "nearest-neighbour gap",
    "rllib_ppo.py": "roco_antialias" if RLLIB else "RLlib is not available",
    "sb3_ppo.py": "roco_antialias" if SB3 else "Stable-Baselines3 is not available",
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
