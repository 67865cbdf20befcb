"""Scoring under attack (roco_env.sweeps.attack) and the attack protocol's grid and tables
(roco_env.sweeps.attack_protocol)."""

from __future__ import annotations

import numpy as np
import pytest

from roco_env.attacks.scoring import EpisodeLog
from roco_env.scenario import scenario_path
from roco_env.sweeps import attack, attack_protocol
from roco_env.sweeps.attack import attack_metrics, clean_twin, run_attack_cell
from roco_env.sweeps.cells import Cell
from roco_env.sweeps.episode import run_cell, run_episode
from roco_env.sweeps.records import record_problem
from roco_env.sweeps.store import ResultStore

SPOOF_10 = (("attack.agents", ["cav_1"]), ("attack.kind", "pose_spoof"),
            ("attack.params.offset_m", 10.0))
ATTACK_FIELDS = {"ap70_clean", "attack_success", "detection_rate", "honest_rejected",
                 "clean_rejected"}


def cell(policy: str, overrides=SPOOF_10, steps: int = 3, scenario="urban_intersection") -> Cell:
    return Cell(scenario, 0.4, policy, 0, steps, overrides=tuple(sorted(overrides)))


@pytest.fixture
def fresh(monkeypatch):
    """No clean episode kept from an earlier test; the keys of the episodes played."""
    attack._clean.clear()
    played = []
    original = attack.timed_episode

    def counted(c, on_step=None):
        played.append(c.key)
        return original(c, on_step=on_step)

    monkeypatch.setattr(attack, "timed_episode", counted)
    yield played
    attack._clean.clear()


@pytest.fixture
def scenario_attack(tmp_path):
    """urban_intersection's file with SPOOF_10 as its own attack section."""
    text = scenario_path("urban_intersection").read_text(encoding="utf-8")
    path = tmp_path / "spoofed.yaml"
    path.write_text(text + "\nattack:\n  kind: pose_spoof\n  agents: [cav_1]\n"
                    "  params: {offset_m: 10.0}\n", encoding="utf-8")
    return str(path)


def test_the_clean_twin_drops_every_attack_override_and_nothing_else(scenario_attack):
    attacked = cell("roco", SPOOF_10 + (("detector", "realistic"),))
    assert clean_twin(attacked).overrides == (("detector", "realistic"),)
    assert clean_twin(cell("roco", ())) == cell("roco", ())
    # a scenario file's own attack is switched off
    twin = clean_twin(cell("roco", (("attack.params.offset_m", 3.0),), scenario=scenario_attack))
    assert twin.overrides == (("attack.kind", "none"), ("attack.params", {}))


def test_an_aligner_that_cannot_reject_detects_nothing_and_the_spoof_costs_it():
    metrics, _, _ = attack_metrics(cell("identity"))
    assert metrics["detection_rate"] == 0.0 and metrics["honest_rejected"] == 0.0
    assert metrics["ap70"] < metrics["ap70_clean"]
    assert 0.0 < metrics["attack_success"] <= 1.0


def test_defend_rejects_exactly_the_attacker_and_its_record_is_valid(tmp_path):
    record = run_attack_cell(cell("defend:base=roco"))
    assert record["status"] == "ok", record.get("traceback")
    store = ResultStore(tmp_path / "results.jsonl")
    store.append(record)
    (stored,) = store.records()
    assert record_problem(stored) is None  # the schema knows the attack metrics
    metrics = record["metrics"]
    assert metrics["detection_rate"] == 1.0
    assert metrics["honest_rejected"] == 0.0 and metrics["clean_rejected"] == 0.0
    assert ATTACK_FIELDS <= set(metrics)
    assert record["time_per_call_ms"] > 0.0  # as every sweep record


def test_the_clean_twin_is_the_cell_without_an_attack_played_once_and_scored_as_a_sweep(fresh):
    metrics, _, _ = attack_metrics(cell("roco"))
    none = cell("roco", ())
    assert fresh == [cell("roco").key, none.key]  # the clean twin is the cell without attack
    scored, _, _ = attack_metrics(none)
    assert fresh == [cell("roco").key, none.key]  # not played again
    alone = run_cell(none)["metrics"]  # the plain sweep's scores of that episode, played anew
    assert {k: scored[k] for k in alone} == pytest.approx(alone, nan_ok=True)
    log = EpisodeLog()
    run_episode(none, on_step=log.on_step)
    assert metrics["ap70_clean"] == log.ap(log.egos - {"cav_1"})[0.7]
    assert scored["ap70_clean"] == scored["ap70"] == log.ap(log.egos)[0.7]
    assert scored["attack_success"] == 0.0 and np.isnan(scored["detection_rate"])
    assert scored["honest_rejected"] == scored["clean_rejected"]


def test_an_episode_without_attackers_is_played_once_per_process(fresh):
    attack_metrics(cell("identity", SPOOF_10, steps=2))
    attack_metrics(cell("identity", (("attack.agents", ["cav_1"]), ("attack.kind", "erase")),
                        steps=2))
    attack_metrics(cell("identity", (), steps=2))  # the attacks' clean twin: not played again
    assert len(fresh) == 3 and len(set(fresh)) == 3


def test_an_attack_of_the_scenario_file_is_scored_against_an_episode_without_it(
        fresh, scenario_attack):
    from_file, _, _ = attack_metrics(cell("identity", (), scenario=scenario_attack))
    from_overrides, _, _ = attack_metrics(cell("identity"))
    assert from_file["ap70"] < from_file["ap70_clean"]
    for key in ("ap70", "ap70_clean", "attack_success", "detection_rate"):
        assert from_file[key] == from_overrides[key], key


def test_the_episode_log_shares_count_only_the_chosen_egos_and_senders():
    log = EpisodeLog(decisions=[("a", "x", True), ("a", "b", False), ("b", "x", False),
                                ("x", "a", True)])
    attackers = frozenset({"x"})
    assert log.rejected(frozenset({"a", "b"}), attackers, True) == 0.5
    assert log.rejected(frozenset({"a", "b"}), attackers, False) == 0.0
    assert np.isnan(log.rejected(frozenset({"c"}), attackers, True))


def test_the_protocol_grid_covers_every_scene_attack_policy_and_seed():
    cells = attack_protocol.protocol_cells(seeds=2, steps=3)
    assert len(cells) == len(attack_protocol.SCENES) * len(attack_protocol.ATTACKS) \
        * len(attack_protocol.POLICIES) * 2
    labels = {attack_protocol.attack_label(c.to_dict()) for c in cells}
    assert labels == set(attack_protocol.ATTACKS)
    assert {attack_protocol.policy_label(c.to_dict()) for c in cells} \
        == set(attack_protocol.POLICIES)  # no_fusion: identity, fusion none
    assert all(dict(c.overrides).get("cavs") == 4 for c in cells if c.scenario == "v2xset_like")


def _record(scenario: str, label: str, policy: str, **metrics) -> dict:
    overrides = {**attack_protocol.PROTOCOL, **attack_protocol.ATTACKS[label]}
    full = {"ap70": 0.7, "ap70_clean": 0.7, "attack_success": 0.0, "detection_rate": 0.0,
            "honest_rejected": 0.0, "clean_rejected": 0.0, **metrics}
    return {"status": "ok", "cell": {"scenario": scenario, "policy": policy, "seed": 0,
                                     "steps": 10, "overrides": overrides}, "metrics": full}


def test_the_report_tables_and_targets():
    records = [
        _record("urban_intersection", "none", "roco", ap70=0.76, ap70_clean=0.76),
        _record("urban_intersection", "none", "defend:base=roco", ap70=0.755,
                ap70_clean=0.755, honest_rejected=0.01),
        _record("urban_intersection", "spoof 10 m", "roco", ap70=0.55, ap70_clean=0.76,
                attack_success=0.99),
        _record("urban_intersection", "spoof 10 m", "defend:base=roco", ap70=0.745,
                ap70_clean=0.76, detection_rate=1.0),
        _record("urban_intersection", "ghosts 5", "defend:base=roco", ap70=0.74,
                ap70_clean=0.76, detection_rate=0.3),
    ]
    text = attack_protocol.render(records)
    assert "| spoof 10 m | 55.0 / 76.0 | 74.5 / 76.0 |" in text
    assert "| spoof 10 m | 1.5 | 100% | 0% | yes |" in text
    assert "| ghosts 5 | 2.0 | 30% | 0% | no |" in text
    assert "| none: cost against roco | 0.5 | - | 1% | yes |" in text
    assert "v2xset_like" not in text


@pytest.mark.parametrize("argv, message", [(["--seeds", "0"], "--seeds and --steps"),
                                            (["--policies", "nope"], "unknown policy")])
def test_bad_protocol_options_are_refused(argv, message, capsys):
    assert attack_protocol.main(argv + ["--out", "unused"]) == 2
    assert message in capsys.readouterr().err
