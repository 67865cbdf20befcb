"""baselines/attack_protocol/replay_defend.py: the protocol's episodes recorded once and
replayed through variants of ``defend``."""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path

import pytest

PATH = Path(__file__).resolve().parents[1] / "baselines" / "attack_protocol" / "replay_defend.py"
_SPEC = importlib.util.spec_from_file_location("replay_defend", PATH)
replay_defend = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(replay_defend)


def test_a_replay_rejects_a_10m_spoofer_and_leaves_out_the_attackers_own_calls():
    """Two steps of the protocol's 10 m spoof on urban_intersection, seed 0 (cav_1 lies):
    every honest ego's defend rejects the attacker on both steps (8 decisions) and none of
    its 3 honest collaborators (24); the attacker's own calls are not counted; a variant
    that switches every test off rejects nobody."""
    calls = replay_defend.record("urban_intersection", "spoof 10 m", 0, 2)
    assert len(calls) == 2 and len(calls[0]) == 5
    attackers, honest = replay_defend.split(replay_defend.decisions(calls, {}))
    assert attackers == [1] * 8 and honest == [0] * 24
    off = replay_defend.parse_variant("use_correction=false,use_consistency=false")
    assert replay_defend.split(replay_defend.decisions(calls, off)) == ([0] * 8, [0] * 24)


def test_variants_and_seeds_are_parsed_and_a_bad_parameter_names_itself():
    assert replay_defend.parse_variant("") == {}
    assert replay_defend.parse_variant("sticky=0,orphan_rate=0.03") == {
        "sticky": 0, "orphan_rate": 0.03}
    assert replay_defend.parse_seeds("2-4") == [2, 3, 4]
    assert replay_defend.parse_seeds("2,5") == [2, 5]
    assert replay_defend.parse_seeds("5,2,5") == [5, 2]  # played once each
    with pytest.raises(ValueError, match=r"sticky=2.0 is out of range"):
        replay_defend.main(["--seeds", "0", "--steps", "1", "--variant", "sticky=2.0"])
    with pytest.raises(ValueError, match=r"base is not a variant parameter"):
        replay_defend.parse_variant("base=identity,sticky=0")


@pytest.mark.parametrize("seeds", ["1-", "-1", "3-1", "a", "1,,2", "1-2-3", ""])
def test_bad_seeds_are_refused_naming_the_option(seeds, capsys):
    with pytest.raises(argparse.ArgumentTypeError, match="--seeds"):
        replay_defend.parse_seeds(seeds)
    with pytest.raises(SystemExit):
        replay_defend.main(["--seeds", seeds, "--steps", "1"])
    assert "--seeds" in capsys.readouterr().err


def test_decisions_name_each_slot_and_details_list_the_misses(capsys):
    """The decisions behind the printed shares (``split``): per honest ego's step and collaborator, whether it
    is the attacker (cav_1 on seed 0), rejected, and why; with every test off, ``--details``
    lists each of the 4 honest egos' missed attacker slots of the one step played."""
    calls = replay_defend.record("urban_intersection", "spoof 10 m", 0, 1)
    found = replay_defend.decisions(calls, {})
    assert len(found) == 16 and {d.step for d in found} == {0}
    liars = [d for d in found if d.attacker]
    assert {d.collaborator for d in liars} == {"cav_1"} and len(liars) == 4
    assert all(d.rejected and d.reason for d in liars)
    assert not any(d.rejected or d.reason for d in found if not d.attacker)
    replay_defend.main(["--seeds", "0", "--steps", "1", "--scenes", "urban_intersection",
                        "--attacks", "spoof 10 m", "--details", "--variant",
                        "use_correction=false,use_consistency=false"])
    missed = [line for line in capsys.readouterr().out.splitlines() if "missed" in line]
    assert len(missed) == 4 and all("seed 0 step 0" in line and "cav_1" in line
                                    for line in missed)
