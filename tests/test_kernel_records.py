"""The compiled (numba) kernels take small named records, not long positional lists.

Every ``@njit`` function of ``roco_env`` is read from its source: none takes more than
MAX_PARAMETERS parameters. A record passed from Python as a plain tuple is named again
inside the kernel, so both forms give the same result.
"""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np

import roco_env
from roco_env.policies.pose_kernels import Solver, wald_statistic

PACKAGE = Path(roco_env.__file__).parent
MAX_PARAMETERS = 8


def _kernels():
    """(module path, name, parameter count) of every numba-compiled function."""
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.FunctionDef) and any(
                    "jit" in ast.unparse(decorator) for decorator in node.decorator_list):
                args = node.args
                count = len(args.posonlyargs) + len(args.args) + len(args.kwonlyargs)
                yield path.relative_to(PACKAGE), node.name, count


def test_no_kernel_takes_a_long_positional_list():
    kernels = list(_kernels())
    assert len(kernels) > 50  # the scan finds the kernels
    long = {name: count for _, name, count in kernels if count > MAX_PARAMETERS}
    assert not long, long


def test_a_record_is_the_same_named_or_plain():
    rng = np.random.default_rng(3)
    landmarks = rng.normal(size=(12, 3)) * [10, 10, 1]
    own = landmarks + rng.normal(size=(12, 3)) * 0.05
    covariance = np.tile(np.diag([0.04, 0.04, 1e-3]), (12, 1, 1))
    solver = Solver(2, 2.0, 100, 1e-6, 1e-9)
    named = wald_statistic(np.zeros(3), landmarks, own, covariance, np.zeros(3), solver)
    plain = wald_statistic(np.zeros(3), landmarks, own, covariance, np.zeros(3), tuple(solver))
    assert named == plain and np.isfinite(named)
