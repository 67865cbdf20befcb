"""The two reference policies: ``identity`` (trust the reported poses) and ``oracle``.

Both are stateless :class:`~roco_env.policies.base.Policy` objects,
``policy(observation, info=None) -> action (N, 3) float32`` (one (dx, dy, dyaw)
correction per collaborator slot, metres and radians, in the ego frame).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from roco_env.policies.base import StatelessPolicy, correction_action


def _slots(observation: Mapping[str, Any]) -> int:
    try:
        return int(np.shape(observation["collab_mask"])[0])
    except (KeyError, TypeError, IndexError) as exc:
        raise ValueError(
            "observation must be a roco_env observation dict with a 'collab_mask' entry of "
            "shape (N,)"
        ) from exc


def _no_params(name: str, params: dict) -> None:
    if params:
        raise ValueError(f"policy {name!r} takes no parameters; got {sorted(params)}")


class IdentityPolicy(StatelessPolicy):
    """Keeps every reported relative pose: the all-zeros correction."""

    def __init__(self, **params: Any) -> None:
        _no_params("identity", params)

    def __call__(self, observation: Mapping[str, Any], info: Mapping | None = None) -> np.ndarray:
        return np.zeros((_slots(observation), 3), dtype=np.float32)


class OraclePolicy(StatelessPolicy):
    """Returns the exact correction from the privileged truth in ``info``.

    Reads ``info["privileged"]["true_relative_poses"]`` and
    ``["reported_relative_poses"]`` (both (N, 3) float64, per slot) and returns
    ``correction_action(reported, true)``. An upper bound for any alignment
    method; it cannot run without the env's info.
    """

    def __init__(self, **params: Any) -> None:
        _no_params("oracle", params)

    def __call__(self, observation: Mapping[str, Any], info: Mapping | None = None) -> np.ndarray:
        privileged = info.get("privileged") if isinstance(info, Mapping) else None
        if not isinstance(privileged, Mapping) or not {
            "true_relative_poses", "reported_relative_poses"
        } <= set(privileged):
            raise ValueError(
                "the oracle policy needs the env's info: call policy(obs[agent], infos[agent]) "
                "with info['privileged'] holding 'true_relative_poses' and "
                "'reported_relative_poses'"
            )
        true = np.asarray(privileged["true_relative_poses"], dtype=float)
        reported = np.asarray(privileged["reported_relative_poses"], dtype=float)
        slots = _slots(observation)
        if true.shape != (slots, 3) or reported.shape != (slots, 3):
            raise ValueError(
                f"info['privileged'] relative poses must have shape ({slots}, 3) to match "
                f"observation['collab_mask']; got {true.shape} and {reported.shape}"
            )
        return correction_action(reported, true)
