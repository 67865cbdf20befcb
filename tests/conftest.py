"""Shared test setup: headless plotting and the `slow` marker policy.

Tests marked ``@pytest.mark.slow`` run only when ROCO_SLOW=1; the default run
(and CI) keeps a representative fast sample so the suite stays well under ten
minutes on a 2-core machine.
"""

import os

import matplotlib
import pytest
from hypothesis import settings

# CI (CI=true) replays the same examples every run so a green main stays green;
# local runs keep exploring new random examples (and the example database).
settings.register_profile("ci", derandomize=True, database=None, print_blob=True)
if os.environ.get("CI", "").lower() == "true":
    settings.load_profile("ci")

matplotlib.use("Agg")
os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
os.environ.setdefault("MPLBACKEND", "Agg")


def pytest_collection_modifyitems(config, items):
    if os.environ.get("ROCO_SLOW") == "1":
        return
    skip = pytest.mark.skip(reason="slow; run with ROCO_SLOW=1")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)
