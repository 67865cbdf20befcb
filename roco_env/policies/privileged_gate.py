"""``privileged_gate``: the perfect rejection, a reference for defences (docs/attacks.md).

``make_policy("privileged_gate", base="roco")`` (spec ``privileged_gate:base=roco``) acts
in the env's ``gate`` action mode behind the aligner ``base`` (it declares both in
:attr:`PrivilegedGate.env_overrides`) and rejects exactly the collaborators that attack,
read from the privileged truth ``info["privileged"]["collab_attackers"]`` (N,) bool by
slot, from the first step on. It is what a defence with perfect detection and no false
alarm scores; it is no defence (no message carries that truth).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from roco_env.policies.base import check_aligner_base
from roco_env.policies.landmarks import params_from_kwargs
from roco_env.schema import spec

__all__ = ["PrivilegedGate", "PrivilegedGateParams"]


@dataclass(frozen=True)
class PrivilegedGateParams:
    """``privileged_gate``'s parameters (module docstring)."""

    base: str = spec("roco", doc="the aligner's policy spec the env runs (action.base)")

    def __post_init__(self) -> None:
        check_aligner_base("privileged_gate", self.base)


class PrivilegedGate:
    """``PrivilegedGate(base="roco")(obs, info) -> (N,) int64`` gate action: 1 for the
    filled slots whose collaborator attacks, else 0."""

    keeps_state = False
    last_result = None  # the env's base aligner aligns

    def __init__(self, **params: Any) -> None:
        self.params = params_from_kwargs(PrivilegedGateParams, params, "privileged_gate")
        self.env_overrides = {"action.mode": "gate", "action.base": self.params.base}

    def reset(self) -> None:
        """Nothing to forget (stateless)."""

    def __call__(self, observation: Mapping[str, Any], info: Mapping | None = None
                 ) -> np.ndarray:
        attackers = ((info or {}).get("privileged") or {}).get("collab_attackers")
        if attackers is None:
            raise ValueError("privileged_gate reads info['privileged']['collab_attackers']: "
                             "call it with the env's info, the privileged truth on "
                             "(info_level='full' or privileged=True)")
        filled = np.asarray(observation["collab_mask"]) > 0
        return (np.asarray(attackers, dtype=bool) & filled).astype(np.int64)
