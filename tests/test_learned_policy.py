"""The shipped learned policy (``learned_select``) and the learned-policy weights loader.

The shipped file must match its recorded sha256 (a retrained file changes it, and the
docs' numbers with it); every bad file is refused with an error naming the file and what
is wrong, without unpickling anything.
"""

from __future__ import annotations

import hashlib
import json
import pickle

import numpy as np
import pytest
import torch

import roco_env
from roco_env.policies import make_policy
from roco_env.policies.learned import SHIPPED, WEIGHTS_DIR, LearnedPolicy
from roco_env.policies.spec import merge_env_overrides
from roco_env.sweeps.cells import Cell
from roco_env.sweeps.episode import run_episode
from roco_env.wrappers import EgoEnv

SHIPPED_SHA256 = {
    "learned_select": "03f972cd5ddfe6ef7ba08e064127bab94101f75d27ee6c5fd805c6220ac1a6bc",
    "learned_fallback": "8816851981dcebd15fedcfe9db016166dee05e6ccc9359d722cdce4e0bb939ae"}
SHIPPED_FILE = WEIGHTS_DIR / SHIPPED["learned_select"][0]


@pytest.mark.parametrize("name", sorted(SHIPPED))
def test_the_shipped_weights_match_their_checksum_and_size(name):
    data = (WEIGHTS_DIR / SHIPPED[name][0]).read_bytes()
    assert hashlib.sha256(data).hexdigest() == SHIPPED_SHA256[name]
    assert len(data) <= 5 * 2**20


def test_the_shipped_policy_declares_its_modes_and_acts_by_slot():
    policy = make_policy("learned_select")
    assert policy.env_overrides["action.mode"] == "select"
    assert policy.env_overrides["observation.mode"] == "aligned"
    env = EgoEnv("v2xset_like", max_cycles=2, others="learned_select", sigma_t=1.0,
                 sigma_r=1.0)
    assert env.env.config.action.mode == "select"  # the others' modes, merged
    observation, info = env.reset(seed=0)
    action = policy(observation, info)
    assert action.shape == (5,) and action.dtype == np.int64
    assert env.action_space.contains(action)
    np.testing.assert_array_equal(policy(observation, info), action)  # deterministic


@pytest.mark.parametrize("name", sorted(SHIPPED))
def test_the_shipped_policy_runs_as_a_sweep_cell_deterministically(name):
    cell = Cell(scenario="v2xset_like", policy=name, noise=1.5, density=None,
                seed=0, steps=2)
    first, _ = run_episode(cell)
    second, _ = run_episode(cell)
    assert first["ap70"] == second["ap70"] and first["frames"] > 0
    assert np.isnan(first["correction_share"])  # select actions are no corrections


def write_weights(path, state=None, **metadata_changes):
    """A copy of the shipped file with its state dict or metadata changed (no guard
    unless one is given)."""
    raw = torch.load(SHIPPED_FILE, weights_only=True)
    metadata = {**json.loads(raw["metadata"]), "guard": None, **metadata_changes}
    torch.save({"state_dict": state or raw["state_dict"], "metadata": json.dumps(metadata)},
               path)
    return str(path)


def test_non_finite_weights_are_refused_naming_the_file(tmp_path):
    state = torch.load(SHIPPED_FILE, weights_only=True)["state_dict"]
    state = {**state, "layers.0.weight": state["layers.0.weight"].clone()}
    state["layers.0.weight"][0, 0] = float("nan")
    path = write_weights(tmp_path / "nan.pt", state)
    with pytest.raises(ValueError, match=r"nan\.pt.*non-finite.*layers\.0\.weight"):
        make_policy("learned_select", weights=path)


def test_weights_of_another_action_mode_are_refused_naming_the_field(tmp_path):
    raw = json.loads(torch.load(SHIPPED_FILE, weights_only=True)["metadata"])
    path = write_weights(tmp_path / "gate.pt",
                         env_overrides={**raw["env_overrides"], "action.mode": "gate"})
    with pytest.raises(ValueError, match=r"gate\.pt: action.mode is 'gate'.*'select'"):
        make_policy("learned_select", weights=path)


def test_an_observation_of_another_mode_or_size_is_refused_naming_the_field():
    policy = make_policy("learned_select")
    raw_env = roco_env.parallel_env("v2xset_like", max_cycles=1)  # raw mode, N = 4
    observations, infos = raw_env.reset(seed=0)
    with pytest.raises(ValueError, match=r"observation.mode='aligned'.*max_collaborators=5"):
        policy(observations["cav_0"], infos["cav_0"])
    small = roco_env.parallel_env("v2xset_like", max_cycles=1,
                                  **{**policy.env_overrides, "max_collaborators": 3})
    observations, _ = small.reset(seed=0)
    with pytest.raises(ValueError, match=r"observation\['choice_diagnostics'\] has shape "
                                         r"\(3, 4, 8\), expected \(5, 4, 8\)"):
        policy(observations["cav_0"])


def test_the_hint_names_the_default_choices_for_a_file_that_records_none():
    """The shipped file predates recorded action.choices: the hint names the default."""
    policy = make_policy("learned_select")
    assert "action.choices" not in policy.env_overrides
    with pytest.raises(ValueError, match=r"action\.choices=the default \(identity, coalign, "
                                         r"roco, roco_antialias\)"):
        policy({})


def test_weights_from_before_the_age_column_are_refused_naming_the_mismatch(tmp_path):
    """A file trained on (N, 8) diagnostics (before ``age_ms``) loads, and acting on
    today's (N, 9) diagnostics is a ValueError naming the entry and both shapes."""
    size = 5 + 5 * 8
    state = {"layers.0.weight": torch.zeros(25, size), "layers.0.bias": torch.zeros(25),
             "input_scale": torch.ones(size, dtype=torch.float64)}
    path = write_weights(tmp_path / "old.pt", state,
                         observation=[["collab_mask", [5]], ["diagnostics", [5, 8]]])
    policy = make_policy("learned_select", weights=path)
    env = roco_env.parallel_env("v2xset_like", max_cycles=1, **policy.env_overrides)
    observations, _ = env.reset(seed=0)
    with pytest.raises(ValueError, match=r"observation\['diagnostics'\] has shape \(5, 9\), "
                                         r"expected \(5, 8\).*old\.pt"):
        policy(observations["cav_0"])


def test_a_pickled_or_malformed_file_is_refused_without_unpickling(tmp_path):
    path = tmp_path / "evil.pt"
    path.write_bytes(pickle.dumps({"state_dict": {}, "metadata": object()}))
    with pytest.raises(ValueError, match="evil.pt"):
        make_policy("learned_select", weights=str(path))
    torch.save({"state_dict": {}, "metadata": "{}"}, tmp_path / "empty.pt")
    with pytest.raises(ValueError, match=r"empty\.pt: metadata lacks"):
        LearnedPolicy(str(tmp_path / "empty.pt"))
    with pytest.raises(ValueError, match="does not exist"):
        make_policy("learned_select", weights=str(tmp_path / "missing.pt"))


def test_a_conflicting_env_override_names_the_field():
    policy = make_policy("learned_select")
    assert merge_env_overrides({"sigma_t": 1.0}, policy)["action.mode"] == "select"
    with pytest.raises(ValueError, match=r"action.mode='select'.*action.mode='gate'"):
        merge_env_overrides({"action.mode": "gate"}, policy, "learned_select")
    with pytest.raises(ValueError, match="action.mode"):
        EgoEnv("v2xset_like", others="learned_select", **{"action.mode": "correction"})


def test_the_weights_file_is_part_of_a_sweeps_provenance():
    """Retrained weights must make the records of the old ones stale."""
    from roco_env.policies.base import policy_input_files

    policy = make_policy("learned_select")
    assert policy_input_files(policy) == (policy.path,)


def test_the_guard_reads_the_statistic_column_of_choice_diagnostics():
    from roco_env.observation_modes import CHOICE_DIAGNOSTICS, DIAGNOSTICS
    from roco_env.policies.reject_untested import NO_STATISTIC, STATISTIC

    for columns in (CHOICE_DIAGNOSTICS, DIAGNOSTICS):  # the guard and reject_untested
        assert columns[STATISTIC][0] == "statistic"
        assert columns[STATISTIC][1] == NO_STATISTIC  # its lower bound: none computed


def test_the_guard_rejects_only_untested_slots_the_network_would_reject():
    """Slot 0: tested (kept whatever the logits); slot 1: untested, reject logit 0.5
    below keep's (rejected only with a margin >= 0.5); slot 2: untested, reject wins;
    slot 3: empty (kept)."""
    from roco_env.policies.learned import Guard

    logits = np.array([[0.0, 0.0, 0.0, 1.0, 9.0],   # would reject, but roco_antialias tested it
                       [0.0, 0.0, 0.0, 1.0, 0.5],
                       [0.0, 0.0, 0.0, 1.0, 2.0],
                       [0.0, 0.0, 0.0, 1.0, 9.0]])
    diagnostics = np.zeros((4, 4, 8))
    diagnostics[:, :, _statistic_column()] = -1.0  # no statistic computed ...
    diagnostics[0, 3, _statistic_column()] = 4.2  # ... but roco_antialias's in slot 0
    mask = np.array([1, 1, 1, 0])
    np.testing.assert_array_equal(Guard(3, 0.0).act(logits, diagnostics, mask), [3, 3, 4, 3])
    np.testing.assert_array_equal(Guard(3, 0.5).act(logits, diagnostics, mask), [3, 4, 4, 3])
    np.testing.assert_array_equal(Guard(3, -5.0).act(logits, diagnostics, mask), [3, 3, 3, 3])


def test_the_rule_guard_rejects_every_untested_slot_and_lets_the_network_decide_the_rest():
    """``train-policy --guard reject_untested``'s guard: the same logits as above; slot 0
    (tested) takes the network's argmax (reject), slots 1 and 2 (untested) are rejected
    whatever the logits, slot 3 (empty) takes the argmax (the env ignores it)."""
    from roco_env.policies.learned import Guard

    logits = np.array([[0.0, 0.0, 0.0, 1.0, 9.0],
                       [0.0, 0.0, 0.0, 1.0, 0.5],
                       [0.0, 2.0, 0.0, 1.0, 0.5],
                       [0.0, 0.0, 3.0, 1.0, 0.0]])
    diagnostics = np.zeros((4, 4, 8))
    diagnostics[:, :, _statistic_column()] = -1.0
    diagnostics[0, 3, _statistic_column()] = 4.2
    diagnostics[3, 3, _statistic_column()] = 1.0
    mask = np.array([1, 1, 1, 0])
    np.testing.assert_array_equal(Guard(3, None, "network").act(logits, diagnostics, mask),
                                  [4, 4, 4, 2])


def test_the_keep_tested_guard_keeps_tested_slots_and_lets_the_network_decide_the_rest():
    """``train-policy --guard keep_tested``'s guard over [roco_antialias, roco_fallback]:
    slot 0 (tested) takes roco_antialias (0) whatever the logits, slots 1 and 2 (untested)
    the network's argmax (reject, roco_fallback), slot 3 (empty) choice 0."""
    from roco_env.policies.learned import Guard

    logits = np.array([[0.0, 1.0, 9.0], [0.0, 1.0, 2.0], [0.0, 3.0, 2.0], [0.0, 1.0, 9.0]])
    diagnostics = np.zeros((4, 2, 8))
    diagnostics[:, :, _statistic_column()] = -1.0
    diagnostics[0, 0, _statistic_column()] = 4.2
    mask = np.array([1, 1, 1, 0])
    guard = Guard(0, None, "keep", "network")
    np.testing.assert_array_equal(guard.act(logits, diagnostics, mask), [0, 2, 1, 0])
    np.testing.assert_array_equal(
        guard.constrain(np.array([2, 2, 1, 1]), 2, diagnostics, mask), [0, 2, 1, 0])


def test_a_file_with_the_rule_guard_loads_it_and_refuses_a_margin(tmp_path):
    from roco_env.policies.learned import Guard, rule_guard

    path = guarded_weights(tmp_path / "rule.pt", rule_guard(3))
    assert make_policy("learned_select", weights=path).guard == Guard(3, None, "network")
    with pytest.raises(ValueError, match=r"rule\.pt: its guard rejects every untested slot"):
        make_policy("learned_select", weights=path, reject_margin=1.0)
    bad = guarded_weights(tmp_path / "bad.pt", {**rule_guard(3), "tested": "keep"})
    with pytest.raises(ValueError, match=r"bad\.pt: guard must be"):
        make_policy("learned_select", weights=bad)


def _statistic_column() -> int:
    from roco_env.policies.reject_untested import STATISTIC

    return STATISTIC


def guarded_weights(path, guard, choices=4):
    """A select-mode file over ``choices`` choices reading choice_diagnostics and
    collab_mask (random network) with ``guard`` in its metadata."""
    torch.manual_seed(0)
    size = 5 * choices * 8 + 5
    state = {"layers.0.weight": torch.randn(8, size), "layers.0.bias": torch.zeros(8),
             "layers.1.weight": torch.randn(5 * (choices + 1), 8),
             "layers.1.bias": torch.zeros(5 * (choices + 1)),
             "input_scale": torch.ones(size, dtype=torch.float64)}
    return write_weights(path, state, guard=guard, action={"nvec": [choices + 1] * 5},
                         observation=[["choice_diagnostics", [5, choices, 8]],
                                      ["collab_mask", [5]]])


def test_the_prefer_guard_takes_the_preferred_choice_within_its_gap_on_tested_slots():
    """keep_tested with prefer 1 within 0.5 m over [roco_antialias, roco_fallback]: tested
    slot 0 (gap 0.2 m) takes 1, tested slot 1 (gap 2.5 m, an alias) 0, untested slot 2 the
    network's argmax whatever the gap; the rule alone rejects slot 2."""
    from roco_env.policies.learned import Guard
    from roco_env.policies.reject_untested import GAP_M

    logits = np.array([[9.0, 0.0, 0.0], [0.0, 9.0, 0.0], [0.0, 9.0, 0.0], [0.0, 0.0, 9.0]])
    diagnostics = np.zeros((4, 2, 8))
    diagnostics[:, :, _statistic_column()] = -1.0
    diagnostics[:2, 0, _statistic_column()] = 4.2
    diagnostics[:, 1, GAP_M] = [0.2, 2.5, 0.1, 0.0]
    mask = np.array([1, 1, 1, 0])
    guard = Guard(0, None, "keep", "network", prefer=1, prefer_within_m=0.5)
    np.testing.assert_array_equal(guard.act(logits, diagnostics, mask), [1, 0, 1, 1])
    np.testing.assert_array_equal(guard.rule(2, diagnostics, mask), [1, 0, 2, 1])
    always = Guard(0, None, "keep", "network", prefer=1)
    np.testing.assert_array_equal(always.rule(2, diagnostics, mask), [1, 1, 2, 1])


def test_a_file_with_the_prefer_guard_loads_it_and_refuses_bad_prefer_fields(tmp_path):
    from roco_env.policies.learned import Guard, keep_tested_guard

    path = guarded_weights(tmp_path / "c.pt", keep_tested_guard(0, 1, 0.5), choices=2)
    assert make_policy("learned_select", weights=path).guard == \
        Guard(0, None, "keep", "network", 1, 0.5)
    old = guarded_weights(tmp_path / "old.pt", keep_tested_guard(0), choices=2)
    assert make_policy("learned_select", weights=old).guard == Guard(0, None, "keep", "network")
    for guard, field, choices in (
            (keep_tested_guard(0, 0, 0.5), "prefer must", 2),  # keep itself
            (keep_tested_guard(0, 2, 0.5), "prefer must", 2),  # not a choice
            (keep_tested_guard(0, 1, 0.5), "prefer must", 4),  # gap_m needs two choices
            ({**keep_tested_guard(0, 1), "prefer": True}, "prefer must", 2),
            (keep_tested_guard(0, 1, 20.0), "prefer_within_m must", 2),
            (keep_tested_guard(0, 1, "near"), "prefer_within_m must", 2),
            ({**keep_tested_guard(0), "prefer_within_m": 0.5}, "must be", 2)):
        bad = guarded_weights(tmp_path / "bad.pt", guard, choices=choices)
        with pytest.raises(ValueError, match=rf"bad\.pt: guard {field}"):
            make_policy("learned_select", weights=bad)


def test_a_guarded_policy_that_never_rejects_is_its_kept_choice(tmp_path):
    """With a margin no logit gap reaches, a guarded policy takes roco_antialias (choice 3)
    in every slot: the same episode score as roco_antialias itself."""
    path = guarded_weights(tmp_path / "never.pt", {"keep": 3, "reject_margin": -1e9})
    scores = [run_episode(Cell(scenario="v2xset_like", policy=policy, noise=3.0, density=None,
                               seed=0, steps=2))[0]["ap70"]
              for policy in (f"learned_select:weights={path}", "roco_antialias")]
    assert scores[0] == scores[1]


def test_bad_guards_and_margins_are_refused_naming_the_field(tmp_path):
    for guard in ({"keep": 4, "reject_margin": 0.0}, {"keep": 3}, [3, 0.0]):
        path = guarded_weights(tmp_path / "bad.pt", guard)
        with pytest.raises(ValueError, match=r"bad\.pt: guard must be"):
            make_policy("learned_select", weights=path)
    path = guarded_weights(tmp_path / "good.pt", {"keep": 3, "reject_margin": 0.0})
    assert make_policy("learned_select", weights=path, reject_margin=1.5).guard.reject_margin \
        == 1.5
    with pytest.raises(ValueError, match="reject_margin"):
        make_policy("learned_select", weights=path, reject_margin=float("nan"))
    unguarded = write_weights(tmp_path / "plain.pt")
    with pytest.raises(ValueError, match=r"plain\.pt has no guard; reject_margin"):
        make_policy("learned_select", weights=unguarded, reject_margin=1.0)


def test_the_shipped_policy_keeps_roco_antialias_on_every_tested_slot():
    """The shipped guard: roco_antialias (choice 3) or reject, and reject only where
    roco_antialias computed no statistic."""
    from roco_env.policies.learned import Guard

    policy = make_policy("learned_select")
    assert policy.guard == Guard(keep=3, reject_margin=2.0)  # docs/learning.md's
    env = roco_env.parallel_env("v2xset_like", max_cycles=2, sigma_t=3.0, sigma_r=3.0,
                                **policy.env_overrides)
    observations, _ = env.reset(seed=1)  # a seed where one slot is untested and rejected
    rejected = 0
    for observation in observations.values():
        action = policy(observation)
        statistic = observation["choice_diagnostics"][:, 3, _statistic_column()]
        assert set(action.tolist()) <= {3, 4}
        assert np.all(statistic[action == 4] == -1.0)
        rejected += int(np.sum(action == 4))
    assert rejected >= 1


def test_learned_fallback_follows_rule_c_on_tested_slots_and_decides_the_untested_ones():
    """learned_fallback (docs/learning.md): select over [roco_antialias, roco_fallback]
    behind the prefer guard; on parking_lot at 3 m / 3 deg (seed 1, every agent, 2 steps)
    its action on every slot roco_antialias tested equals hand rule C's, and it decides
    some untested slots."""
    from roco_env.policies.learned import Guard
    from roco_env.policies.reject_untested import STATISTIC
    from roco_env.policies.spec import parse_policy_spec

    policy = make_policy("learned_fallback")
    assert policy.guard == Guard(0, None, "keep", "network", prefer=1, prefer_within_m=0.5)
    rule_c = parse_policy_spec("reject_untested:tested=roco_fallback,tested_within_m=0.5"
                               ).build()
    assert policy.env_overrides == {**rule_c.env_overrides, "max_collaborators": 5,
                                    "max_boxes": 64}
    env = roco_env.parallel_env("parking_lot", max_cycles=2, sigma_t=3.0, sigma_r=3.0,
                                **policy.env_overrides)
    observations, infos = env.reset(seed=1)
    untested = 0
    while env.agents:
        actions = {}
        for agent in env.agents:
            observation = observations[agent]
            actions[agent] = action = policy(observation, infos[agent])
            filled = observation["collab_mask"] > 0
            blind = filled & (observation["choice_diagnostics"][:, 0, STATISTIC] == -1)
            np.testing.assert_array_equal(action[filled & ~blind],
                                          rule_c(observation)[filled & ~blind])
            untested += int(blind.sum())
        observations, _, _, _, infos = env.step(actions)
    assert untested >= 1
