"""Users' own policies by import target and entry point; one policy instance for all agents."""

import textwrap

import numpy as np
import pytest

import roco_env
from roco_env.cli import main
from roco_env.policies import available_policies, make_policy
from roco_env.policies.spec import merge_env_overrides
from roco_env.sweeps.text_specs import parse_policy_spec, validate_policy_spec

PLUGIN = textwrap.dedent('''
    import numpy as np

    def make_policy(gain=0.0):
        def policy(obs, info=None):
            return np.full((obs["collab_mask"].shape[0], 3), gain, dtype=np.float32)
        return policy

    def make_short():  # forgets that the action has one row per collaborator *slot*
        return lambda obs, info=None: np.zeros((2, 3))

    def make_nothing():  # forgets to return the policy
        pass
''')


@pytest.fixture
def plugin(tmp_path, monkeypatch):
    """A module my_plugin_mod on sys.path and an installed distribution registering it."""
    (tmp_path / "my_plugin_mod.py").write_text(PLUGIN)
    install_plugin(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    return tmp_path


def test_import_target_builds_the_users_policy(plugin):
    policy = make_policy("my_plugin_mod:make_policy", gain=0.0)
    obs = {"collab_mask": np.ones(5, dtype=np.int8)}
    assert policy(obs).shape == (5, 3)
    spec = parse_policy_spec("my_plugin_mod:make_policy:gain=0.5")
    assert spec.name == "my_plugin_mod:make_policy" and dict(spec.params) == {"gain": 0.5}
    assert spec.label == "my_plugin_mod:make_policy:gain=0.5"
    assert parse_policy_spec(spec.label) == spec


def test_entry_point_registers_a_name(plugin):
    assert "mine" in available_policies()
    assert make_policy("mine", gain=1.0)({"collab_mask": np.ones(2)})[0, 0] == 1.0


def test_compare_runs_a_users_policy_from_the_cli(plugin, tmp_path, capsys):
    code = main(["compare", "--policies", "my_plugin_mod:make_policy", "mine", "--noise", "0.2",
                 "--seeds", "1", "--steps", "2", "--workers", "1", "--no-plots", "--quiet",
                 "--set", "cavs=2", "--set", "rsus=0", "--out", str(tmp_path / "out")])
    assert code == 0
    out = capsys.readouterr().out
    assert "my_plugin_mod:make_policy" in out and "mine" in out


def install_plugin(folder):
    """Write the installed-distribution metadata that registers ``mine``."""
    dist = folder / "my_plugin-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: my-plugin\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text(
        "[roco_env.policies]\nmine = my_plugin_mod:make_policy\n")


def test_entry_points_are_scanned_once_per_path(plugin, monkeypatch):
    import importlib.metadata

    scans = []
    real = importlib.metadata.entry_points

    def counting(**kwargs):
        scans.append(kwargs)
        return real(**kwargs)

    monkeypatch.setattr(importlib.metadata, "entry_points", counting)
    monkeypatch.syspath_prepend(str(plugin / "elsewhere"))  # a new path: one new scan
    for _ in range(3):
        make_policy("identity")
        make_policy("mine", gain=1.0)
    assert "mine" in available_policies() and len(scans) == 1


def test_a_plugin_installed_after_a_scan_is_found(tmp_path, monkeypatch):
    (tmp_path / "my_plugin_mod.py").write_text(PLUGIN)
    monkeypatch.syspath_prepend(str(tmp_path))
    assert "mine" not in available_policies()  # scanned without it
    install_plugin(tmp_path)  # same sys.path: the cached scan does not know it
    assert make_policy("mine", gain=1.0)({"collab_mask": np.ones(2)})[0, 0] == 1.0


def test_bad_targets_say_what_is_wrong(plugin):
    with pytest.raises(ValueError, match="cannot import module 'no_such_mod'"):
        make_policy("no_such_mod:make")
    with pytest.raises(ValueError, match="has no callable 'nothing'"):
        make_policy("my_plugin_mod:nothing")
    with pytest.raises(ValueError, match="unknown policy 'magic'"):
        make_policy("magic")


def test_policy_parameter_of_the_wrong_type_is_named():
    with pytest.raises(ValueError, match="tau2 expects a number; got 'abc'"):
        validate_policy_spec("roco:tau2=abc")
    assert make_policy("roco", tau2=np.float32(2.0)).params.tau2 == 2.0


def _episode_actions(policy_for, steps=3, modes=None):
    """Every step's actions; ``modes``: a policy whose env_overrides the env takes."""
    overrides = merge_env_overrides({"cavs": 3, "rsus": 1, "density": 2.0, "sigma_t": 0.6,
                                     "sigma_r": 0.6, "noise_model": "bias"}, modes)
    env = roco_env.parallel_env("urban_intersection", max_cycles=steps, **overrides)
    obs, infos = env.reset(seed=3)
    actions_seen = []
    while env.agents:
        actions = {a: policy_for(a)(obs[a], infos[a]) for a in env.agents}
        actions_seen.append(actions)
        obs, _, _, _, infos = env.step(actions)
    return actions_seen


@pytest.mark.parametrize("name", available_policies())
def test_a_shared_policy_acts_as_one_per_agent(name):
    shared = make_policy(name)
    own = {}
    per_agent = _episode_actions(lambda a: own.setdefault(a, make_policy(name)), modes=shared)
    together = _episode_actions(lambda a: shared, modes=shared)
    for step_a, step_b in zip(per_agent, together, strict=True):
        for agent in step_a:
            np.testing.assert_array_equal(step_a[agent], step_b[agent])


def test_list_names_the_stateful_policies(capsys):
    assert main(["list", "policies"]) == 0
    lines = capsys.readouterr().out.splitlines()
    stateful = {line.split()[0] for line in lines if "stateful" in line}
    assert stateful == {"roco_temporal", "coalign_temporal", "roco_antialias", "defend",
                        "compensate"}


def test_a_plugin_without_a_policy_is_refused_before_the_sweep(plugin):
    with pytest.raises(ValueError, match=r"policy spec 'my_plugin_mod:make_nothing': what "
                                         r"my_plugin_mod:make_nothing\(\) returned must be a "
                                         r"policy\(obs, info\) -> action; got None"):
        validate_policy_spec("my_plugin_mod:make_nothing")


def test_a_plugin_action_of_the_wrong_shape_names_the_shape(plugin, capsys):
    assert main(["run", "--policy", "my_plugin_mod:make_short", "--steps", "1",
                 "--set", "cavs=2", "--set", "rsus=1"]) == 2
    assert ("action for agent 'cav_0' must have shape (5, 3) = (dx m, dy m, dyaw rad) per "
            "collaborator slot; got (2, 3)") in capsys.readouterr().err
