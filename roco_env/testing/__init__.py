"""Helpers for the tests and the benchmarks, not for running the env.

Nothing in the environment, the policies or the command line imports this package
(tests/test_layers.py puts it above everything but the benchmarks). It ships with
the wheel because ``python -m roco_env.benchmarks`` times alignment on its scenes.

* :mod:`roco_env.testing.constructed_scenes`: alignment scenes with known pose errors
  (objects in a world frame, each agent's boxes in its true frame, each collaborator's
  reported pose its true pose perturbed by a chosen error), and their env observation.
"""
