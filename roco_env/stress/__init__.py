"""Falsification search: find the scenarios where an alignment policy breaks.

``roco-env stress`` (roco_env/cli/stress.py) drives it; the modules each do one job:
:mod:`~roco_env.stress.space` (the parameters and their ranges, the scenario of one
evaluation), :mod:`~roco_env.stress.objectives` (an evaluation's objective from episode
samples), :mod:`~roco_env.stress.study` (the Optuna study in SQLite, workers, resuming)
and :mod:`~roco_env.stress.stress_report` (the worst scenarios, report.md, plot, importances).
See docs/stress.md.
"""
