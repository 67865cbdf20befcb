"""Policy comparison sweeps: grid -> episodes on a backend -> JSONL results -> report.

    from roco_env.sweeps import build_grid, run_sweep, write_report
    cells = build_grid(["crowded_intersection"], noises=[0.0, 0.4], policies=["identity", "roco"],
                       seeds=[0, 1], steps=20)
    outcome = run_sweep(cells, "runs/cmp/results.jsonl", backend="local")
    print(write_report(outcome.records, "runs/cmp").markdown)
"""

from roco_env.sweeps.cells import Cell, build_grid, validate_grid
from roco_env.sweeps.sweep import run_sweep
from roco_env.sweeps.sweep_report import write_report

__all__ = ["Cell", "build_grid", "run_sweep", "validate_grid", "write_report"]
