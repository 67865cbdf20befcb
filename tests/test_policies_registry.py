"""The policy registry: built-ins, user registration and its errors."""

from __future__ import annotations

import pytest

import roco_env.policies as policies
from roco_env.policies import available_policies, make_policy, register_policy


@pytest.fixture(autouse=True)
def private_registry(monkeypatch):
    monkeypatch.setattr(policies, "_REGISTRY", dict(policies._REGISTRY))


def test_builtins_are_listed():
    assert {"identity", "oracle", "coalign", "roco"} <= set(available_policies())


def test_registered_policy_is_made_fresh_each_call():
    register_policy("my_roco", "roco_env.policies.roco:RoCoPolicy")
    assert "my_roco" in available_policies()
    first, second = make_policy("my_roco", tau2=2.0), make_policy("my_roco", tau2=2.0)
    assert type(first).__name__ == "RoCoPolicy" and first is not second


def test_bad_registration_and_unknown_names_are_named():
    with pytest.raises(ValueError, match="module:factory"):
        register_policy("broken", "roco_env.policies.basic.IdentityPolicy")
    with pytest.raises(ValueError, match="unknown policy 'nope'"):
        make_policy("nope")


def test_a_spec_string_and_unknown_parameters_are_explained():
    with pytest.raises(ValueError, match=r"keyword arguments, make_policy\('roco', \.\.\.\)"):
        make_policy("roco:tau2=2")
    for name in ("identity", "oracle"):
        with pytest.raises(ValueError, match=f"policy '{name}' takes no parameters"):
            make_policy(name, tau2=2)


@pytest.mark.parametrize("name", sorted(policies.registered_policies()))
def test_every_builtin_refuses_an_unknown_parameter_by_name(name):
    with pytest.raises(ValueError, match="no_such_key"):
        make_policy(name, no_such_key=1)


def test_a_policy_spec_is_checked_by_its_policy():
    from roco_env.policies.spec import validate_policy_spec

    with pytest.raises(ValueError, match=r"policy spec 'ransac:min_inliers=0': ransac: "
                                         r"min_inliers=0 is out of range; allowed \[1, inf\)"):
        validate_policy_spec("ransac:min_inliers=0")
    with pytest.raises(ValueError, match=r"policy spec 'roco:pooled_significance=0.9,"
                                         r"significance=null': pooled_significance needs"):
        validate_policy_spec("roco:pooled_significance=0.9,significance=null")
