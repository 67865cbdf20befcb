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
