"""With the network off (``comm.delay: none``, the default) episodes are bit-identical to
those of the code before the network stage existed: digests of seeded episodes (every
observation, reward and info, byte for byte) pinned in tests/data/network_off.json,
recorded with that code. The comm stage's own random stream is spawned after the other
three, so turning it on changes no draw of traffic, noise or sensing either.

Regenerate (only for a deliberate, documented change of results) with
``python tests/test_network_off.py``.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import roco_env

RECORD = Path(__file__).parent / "data" / "network_off.json"
# (scenario, overrides, seed, steps): an RSU crossing, a dense highway, the realistic
# detector with pose noise, and select mode (which runs the env's aligners).
CASES = (
    ("urban_intersection", {}, 3, 4),
    ("highway_dense", {"sigma_t": 0.4, "sigma_r": 0.4}, 5, 4),
    ("crowded_intersection", {"noise_model": "ar1", "cavs": 3}, 1, 3),
    ("v2x_crossroad", {"action.mode": "select"}, 2, 3),
)


def _feed(digest: Any, value: object) -> None:
    """Every number, array and text of ``value`` (nested dicts by sorted key) into the digest."""
    if isinstance(value, dict):
        for key in sorted(value, key=str):
            digest.update(str(key).encode())
            _feed(digest, value[key])
    elif isinstance(value, (list, tuple)):
        digest.update(f"[{len(value)}".encode())
        for item in value:
            _feed(digest, item)
    elif isinstance(value, (np.ndarray, np.generic, float, int, bool)):
        array = np.asarray(value)
        digest.update(f"{array.dtype}{array.shape}".encode())
        digest.update(np.ascontiguousarray(array).tobytes())
    else:
        digest.update(repr(value).encode())


def episode_digest(scenario: str, overrides: dict, seed: int, steps: int) -> str:
    """sha256 of a seeded episode's observations, rewards and infos (zero actions in the
    correction mode, the first choice in select mode)."""
    env = roco_env.parallel_env(scenario, max_cycles=steps, **overrides)
    digest = hashlib.sha256()
    observations, infos = env.reset(seed=seed)
    _feed(digest, [observations, infos])
    while env.agents:
        actions = {a: np.zeros(env.action_space(a).shape, dtype=env.action_space(a).dtype)
                   for a in env.agents}
        _feed(digest, env.step(actions))
    return digest.hexdigest()


def _key(case: tuple) -> str:
    scenario, overrides, seed, steps = case
    return f"{scenario}|{json.dumps(overrides, sort_keys=True)}|seed={seed}|steps={steps}"


@pytest.mark.parametrize("case", CASES, ids=lambda case: case[0])
def test_network_off_episodes_are_bit_identical_to_the_recorded_ones(case):
    recorded = json.loads(RECORD.read_text())
    assert episode_digest(*case) == recorded[_key(case)]


if __name__ == "__main__":
    RECORD.write_text(json.dumps({_key(case): episode_digest(*case) for case in CASES},
                                 indent=1) + "\n")
    print(f"wrote {RECORD}")
