"""With the network off (``comm.delay: none``, the default) episodes are bit-identical to
those of the code before the network stage existed: digests of seeded episodes (every
observation, reward and info, byte for byte) pinned in tests/data/network_off.json,
recorded with that code (re-recorded once since: the privileged info gained the attack
stage's truth, ``attacker`` and ``collab_attackers``; with those two entries left out the
digests were those of the first record). The comm stage's own random stream is spawned after the other
three, so turning it on changes no draw of traffic, noise or sensing either.

Regenerate (only for a deliberate, documented change of results) with
``python tests/test_network_off.py``.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import episode_digest

RECORD = Path(__file__).parent / "data" / "network_off.json"
# (scenario, overrides, seed, steps): an RSU crossing, a dense highway, the realistic
# detector with pose noise, and select mode (which runs the env's aligners).
CASES = (
    ("urban_intersection", {}, 3, 4),
    ("highway_dense", {"sigma_t": 0.4, "sigma_r": 0.4}, 5, 4),
    ("crowded_intersection", {"noise_model": "ar1", "cavs": 3}, 1, 3),
    ("v2x_crossroad", {"action.mode": "select"}, 2, 3),
)


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
