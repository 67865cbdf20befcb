"""The ``python -m`` commands the docs show: their usage names the command, bad input exits 2."""

from __future__ import annotations

import importlib

import pytest


@pytest.mark.parametrize("module", ["roco_env.benchmarks.__main__",
                                    "roco_env.training.assessment",
                                    "roco_env.sweeps.baselines",
                                    "roco_env.sweeps.attack_protocol",
                                    "roco_env.training.rl.attacker"])
def test_usage_names_the_command_to_type(module, capsys):
    command = module.removesuffix(".__main__")
    with pytest.raises(SystemExit) as exit_info:
        importlib.import_module(module).main(["--help"])
    assert exit_info.value.code == 0
    assert capsys.readouterr().out.startswith(f"usage: python -m {command} ")


def test_unknown_benchmark_module_lists_the_available_ones(capsys):
    from roco_env.benchmarks.__main__ import main

    with pytest.raises(SystemExit) as exit_info:
        main(["alignmnet"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "unknown benchmark module 'alignmnet'; available: alignment, ego, env_step," in err
