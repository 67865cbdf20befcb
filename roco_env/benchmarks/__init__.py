"""Micro-benchmarks behind ``make bench``.

Each module of this package exposes ``run(quick: bool) -> list[str]`` returning
printed lines (medians and speed ratios against a baseline measured in the same
process). ``python -m roco_env.benchmarks [name ...]`` runs them all or the named ones.
"""
