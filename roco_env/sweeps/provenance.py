"""What produced a sweep record: the fingerprint that decides whether it may be reused.

A record is reused on resume only when its ``provenance`` equals the one the
current code computes for its cell: a hash of the scenario's *content* after the
cell's overrides (so editing a scenario YAML in place, or a default changing,
invalidates it; its path alone would not), every override (noise, density and
``--set`` values), the policy spec, seed and steps, the package version and a
hash of the package's files (source and packaged data). Anything else is stale
and is recomputed. A replayed dataset's files are not hashed: ``traffic.path`` is part of the
content, the recording behind it is assumed not to change.
"""

from __future__ import annotations

import functools
import hashlib
import json
from pathlib import Path
from typing import Any

import roco_env
from roco_env.scenario import load_scenario, scenario_to_dict
from roco_env.sweeps.grid import Cell

PACKAGE_ROOT = Path(roco_env.__file__).resolve().parent


@functools.cache
def source_hash() -> str:
    """SHA-256 over every file of the package (paths and bytes): code and packaged data
    such as detector weights; bytecode caches are left out."""
    digest = hashlib.sha256()
    for path in sorted(PACKAGE_ROOT.rglob("*")):
        if path.is_file() and "__pycache__" not in path.parts and path.suffix != ".pyc":
            digest.update(path.relative_to(PACKAGE_ROOT).as_posix().encode())
            digest.update(b"\0")
            digest.update(path.read_bytes())
    return digest.hexdigest()


def _digest(data: Any) -> str:
    text = json.dumps(data, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


class Provenance:
    """Fingerprints of cells (each distinct scenario + overrides is loaded once)."""

    def __init__(self) -> None:
        self._scenarios: dict[tuple, Any] = {}

    def _scenario_content(self, cell: Cell) -> Any:
        overrides = tuple(sorted(cell.env_overrides().items()))
        key = (cell.scenario, overrides)
        if key not in self._scenarios:
            try:
                content = scenario_to_dict(load_scenario(cell.scenario, **dict(overrides)))
            except (ValueError, OSError) as exc:  # the cell itself will record the error
                content = {"unloadable": cell.scenario, "error": f"{type(exc).__name__}: {exc}"}
            self._scenarios[key] = content
        return self._scenarios[key]

    def of(self, cell: Cell) -> str:
        """The cell's fingerprint (hex)."""
        return _digest({
            "scenario": self._scenario_content(cell),
            "overrides": cell.env_overrides(),
            "policy": cell.policy,
            "seed": cell.seed,
            "steps": cell.steps,
            "version": roco_env.__version__,
            "source": source_hash(),
        })

    def current(self, record: dict) -> bool:
        """Whether ``record`` was produced by what the current code would run for its cell."""
        try:
            cell = Cell.from_dict(record["cell"])
        except (KeyError, TypeError, ValueError):
            return False
        return record.get("provenance") == self.of(cell)
