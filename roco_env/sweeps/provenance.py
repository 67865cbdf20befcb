"""What produced a sweep record: the fingerprint that decides whether it may be reused.

A record is reused on resume only when its ``provenance`` equals the one the
current code computes for its cell: a hash of the scenario's *content* after the
cell's overrides (so editing a scenario YAML in place, or a default changing,
invalidates it; its path alone would not), every override (noise, density and
``--set`` values), the policy spec, seed and steps, the package version, a hash
of the package's files (source and packaged data) and the content of every other
file the cell reads (:func:`scenario_input_files`, :func:`policy_input_files`):
the learned detector's ``detector.params.weights``, a replay's label files under
``traffic.path``, and the files a policy declares through
:class:`roco_env.policies.base.ReadsFiles`. Anything else is stale and is recomputed.

File contents are hashed once per process while a file's (path, size, mtime_ns)
stay the same (:func:`file_hash`), so a sweep over a big replay folder reads it once.
"""

from __future__ import annotations

import functools
import hashlib
import json
from pathlib import Path
from typing import Any

import roco_env
from roco_env.policies.base import policy_input_files as declared_files
from roco_env.scenario import ScenarioConfig, load_scenario, scenario_to_dict
from roco_env.sweeps.cells import Cell
from roco_env.sweeps.text_specs import parse_policy_spec

PACKAGE_ROOT = Path(roco_env.__file__).resolve().parent

# traffic.source values that replay a dataset folder (traffic.path), and the files of it
# they read: labels and poses (roco_env.traffic.replay reads no point clouds or images,
# which can be gigabytes that would only slow the hash down).
REPLAY_SOURCES = ("opv2v", "dair")
REPLAY_SUFFIXES = (".yaml", ".yml", ".json")

# sha256 (hex) by (absolute path, size in bytes, mtime in ns): see file_hash.
_FILE_HASHES: dict[tuple[str, int, int], str] = {}


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


def file_hash(path: Path) -> str:
    """SHA-256 (hex) of the file's bytes, read once per process while its (absolute path,
    size, mtime_ns) stay the same. OSError when it cannot be read."""
    stat = path.stat()
    key = (str(path.resolve()), stat.st_size, stat.st_mtime_ns)
    if key not in _FILE_HASHES:
        with path.open("rb") as handle:
            _FILE_HASHES[key] = hashlib.file_digest(handle, "sha256").hexdigest()
    return _FILE_HASHES[key]


def content_hashes(path: Path, suffixes: tuple[str, ...] | None = None) -> Any:
    """The content a cell reads at ``path``: a file's hash; for a folder, every file's
    hash under it by relative path (only names ending in ``suffixes`` when given); for
    a path that cannot be read, why (the cell itself will fail on it)."""
    try:
        if not path.is_dir():
            return file_hash(path)
        return {file.relative_to(path).as_posix(): file_hash(file)
                for file in sorted(path.rglob("*"))
                if file.is_file() and (suffixes is None or file.suffix.lower() in suffixes)}
    except OSError as exc:
        return f"unreadable: {type(exc).__name__}: {exc.strerror}"


def scenario_input_files(config: ScenarioConfig) -> dict[str, Any]:
    """Content hashes of the files the scenario makes a cell read, by setting name: the
    learned detector's weights (the shipped ones are in :func:`source_hash`) and a
    replay's label files."""
    files = {}
    weights = config.detector.params.get("weights") if config.detector.preset == "learned" \
        else None
    if weights:
        files["detector.params.weights"] = content_hashes(Path(weights))
    if config.traffic.source in REPLAY_SOURCES and config.traffic.path:
        files["traffic.path"] = content_hashes(Path(config.traffic.path), REPLAY_SUFFIXES)
    return files


def policy_input_files(policy: str) -> dict[str, Any]:
    """Content hashes of the files the policy spec's policy declares it reads, by path."""
    built = parse_policy_spec(policy).build()
    return {str(path): content_hashes(path) for path in declared_files(built)}


def _digest(data: Any) -> str:
    text = json.dumps(data, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _unloadable(what: str, exc: Exception) -> dict[str, str]:
    """Stand-in content of a scenario or policy that fails (the cell records the error)."""
    return {"unloadable": what, "error": f"{type(exc).__name__}: {exc}"}


class Provenance:
    """Fingerprints of cells (each distinct scenario + overrides and each policy spec is
    loaded, and its files hashed, once per instance)."""

    def __init__(self) -> None:
        self._scenarios: dict[tuple, Any] = {}
        self._policies: dict[str, Any] = {}

    def _scenario_content(self, cell: Cell) -> Any:
        overrides = tuple(sorted(cell.env_overrides().items()))
        key = (cell.scenario, overrides)
        if key not in self._scenarios:
            try:
                config = load_scenario(cell.scenario, **dict(overrides))
                content = {"scenario": scenario_to_dict(config),
                           "files": scenario_input_files(config)}
            except (ValueError, OSError) as exc:  # the cell itself will record the error
                content = _unloadable(cell.scenario, exc)
            self._scenarios[key] = content
        return self._scenarios[key]

    def _policy_content(self, policy: str) -> Any:
        if policy not in self._policies:
            try:
                self._policies[policy] = policy_input_files(policy)
            except Exception as exc:  # noqa: BLE001 - any policy error: the cell records it
                self._policies[policy] = _unloadable(policy, exc)
        return self._policies[policy]

    def of(self, cell: Cell) -> str:
        """The cell's fingerprint (hex)."""
        return _digest({
            "scenario": self._scenario_content(cell),
            "overrides": cell.env_overrides(),
            "policy": cell.policy,
            "policy_files": self._policy_content(cell.policy),
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
