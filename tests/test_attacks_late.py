"""The attack and network stages together: an attacker's message the network delivers late
is forged like a fresh one (the attack reads the received boxes' own object ids, not the
sender's current detections), and episodes repeat with the seed."""

from __future__ import annotations

import pytest
from conftest import episode_digest

LATE = {"comm.delay": "fixed", "comm.delay_params.delay_ms": 200}
ATTACKS = (
    {"attack.kind": "pose_spoof", "attack.params.consistent": True},
    {"attack.kind": "ghost", "attack.params.placement": "aliasing"},
    {"attack.kind": "erase", "attack.params.share": 0.5},
)


@pytest.mark.parametrize("attack", ATTACKS, ids=lambda a: a["attack.kind"])
def test_every_attack_runs_on_late_messages_and_repeats(attack):
    overrides = {**LATE, **attack, "attack.agents": ["cav_1"]}
    first = episode_digest("urban_intersection", overrides, 0, 4)
    assert first == episode_digest("urban_intersection", overrides, 0, 4)
    assert first != episode_digest("urban_intersection", LATE, 0, 4)
