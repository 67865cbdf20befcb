"""Every benchmark module behind ``make bench`` runs (``--quick``) and reports lines.

Speed itself is never asserted here (benchmarks print ratios; see the README); this
only keeps ``make bench`` from breaking unnoticed when an API it measures changes.
"""

from __future__ import annotations

import importlib
import pkgutil

import pytest
import torch

import roco_env.benchmarks as benchmarks

# The sweep benchmark starts worker pools (about 25 s): with the slow tests.
SLOW = {"sweep_backends"}
MODULES = sorted(m.name for m in pkgutil.iter_modules(benchmarks.__path__)
                 if not m.name.startswith("_"))


@pytest.mark.parametrize("name", [
    pytest.param(name, marks=pytest.mark.slow if name in SLOW else ()) for name in MODULES])
def test_every_benchmark_module_runs_quick(name):
    threads = torch.get_num_threads()
    lines = importlib.import_module(f"roco_env.benchmarks.{name}").run(quick=True)
    assert lines and all(isinstance(line, str) and line for line in lines)
    assert torch.get_num_threads() == threads  # a benchmark leaves torch as it found it
