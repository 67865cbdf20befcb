"""The attack and network stages together: an attacker's message the network delivers late
is forged like a fresh one (the attack reads the received boxes' own object ids, not the
sender's current detections), once, when it arrives: a scan the ego holds on over later
steps keeps its forged form, so the tracks of the ``compensate`` wrapper (which assume a
held scan does not change) run under every attack; and episodes repeat with the seed."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import episode_digest

from roco_env.pipeline import Pipeline
from roco_env.policies import make_policy
from roco_env.scenario import load_scenario
from roco_env.stages import available_stages

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


def _compensate():
    return make_policy("compensate", base="identity")


@pytest.mark.parametrize("kind", [k for k in available_stages("attack") if k != "none"])
def test_compensate_under_a_random_delay_runs_under_every_attack_and_repeats(kind):
    # a uniform delay holds scans over several steps; erase once crashed the tracks here
    overrides = {"cavs": 3, "delay": "uniform", "delay_ms": 300, "attack.kind": kind,
                 "attack.agents": ["cav_1"]}
    first = episode_digest("highway_dense", overrides, 1, 6, _compensate)
    assert first == episode_digest("highway_dense", overrides, 1, 6, _compensate)
    assert first != episode_digest("highway_dense", {**overrides, "attack.kind": "none"}, 1, 6,
                                   _compensate)


def test_a_held_scan_keeps_the_form_it_was_forged_in():
    config = load_scenario("highway_dense", cavs=3, delay="uniform", delay_ms=300,
                           **{"attack.kind": "erase", "attack.agents": ["cav_1"],
                              "attack.params.share": 0.5})
    pipeline = Pipeline(config)
    frames = [pipeline.reset(np.random.default_rng(1))]
    frames += [pipeline.advance() for _ in range(8)]
    held = 0
    for before, frame in zip(frames[:-1], frames[1:], strict=True):
        for ego in (0, 2):
            view, last = frame.views[ego], before.views[ego]
            if 1 not in view.collaborators or 1 not in last.collaborators:
                continue
            slot, last_slot = view.collaborators.index(1), last.collaborators.index(1)
            if not view.collab_new[slot]:
                held += 1
                np.testing.assert_array_equal(view.collab_boxes[slot],
                                              last.collab_boxes[last_slot])
                np.testing.assert_array_equal(view.collab_object_ids[slot],
                                              last.collab_object_ids[last_slot])
    assert held > 0
