"""What an installed copy needs: the scenario library as package data, a torch-free import."""

import importlib.resources
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
from conftest import run_python

import roco_env
from roco_env.scenario import library_dir

ROOT = Path(__file__).resolve().parents[1]


def test_scenario_library_is_package_data():
    packaged = importlib.resources.files("roco_env") / "scenarios"
    assert packaged.is_dir()
    source = sorted(p.name for p in (ROOT / "scenarios").glob("*.yaml"))
    assert sorted(p.name for p in packaged.iterdir() if p.name.endswith(".yaml")) == source
    assert library_dir() == Path(str(packaged))
    assert roco_env.list_scenarios() == [name.removesuffix(".yaml") for name in source]


@pytest.mark.slow
def test_wheel_ships_every_scenario(tmp_path):
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", "-w",
                    str(tmp_path), str(ROOT)], check=True)
    (wheel,) = tmp_path.glob("roco_env-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    for yaml_file in (ROOT / "scenarios").glob("*.yaml"):
        assert f"roco_env/scenarios/{yaml_file.name}" in names
    assert "roco_env/stress/default_space.yaml" in names  # roco-env stress's default space


_TORCH_PROBE = """
import sys
import numpy as np
import roco_env
assert "torch" not in sys.modules, "import roco_env loaded torch"
env = roco_env.parallel_env("urban_intersection", max_cycles=2)
env.reset(seed=0)
env.step({a: np.zeros(env.action_space(a).shape, np.float32) for a in env.agents})
print("torch" in sys.modules)
"""


def test_import_and_default_env_do_not_load_torch():
    assert run_python(_TORCH_PROBE) == "False"


def test_features_still_load_torch_on_demand():
    probe = ("import sys, roco_env; env = roco_env.parallel_env(features=True, max_cycles=1); "
             "env.reset(seed=0); print('torch' in sys.modules)")
    assert run_python(probe) == "True"
