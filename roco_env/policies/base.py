"""What every alignment policy shares: the :class:`Policy` protocol, the result type
and observation helpers.

A policy is called as ``policy(observation, info=None) -> action``; in the default
action mode the action (N, 3) holds one correction (dx, dy, dyaw) per collaborator
slot, in the ego frame: ``T_corrected_{j->i} = SE2(dx, dy, dyaw) * T_reported_{j->i}``
(metres, radians). Zeros trust the reported poses. Besides the call, a
:class:`Policy` has ``reset()`` (a new episode), ``keeps_state`` (whether, and what,
it keeps across calls) and ``last_result`` (its last :class:`AlignmentResult`, so a
sweep can score its matching). Every built-in policy is one; :func:`as_policy` gives
any other callable (a plain function) the members it lacks. A policy that reads files
(learned weights, lookup tables) declares them with an ``input_files()`` method
(:class:`ReadsFiles`), so a sweep's resume check covers their content. A policy run
around an inner one (temporal smoothing, delay compensation) is a :class:`PolicyWrapper`.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from roco_env.geometry import apply_correction, se2_compose, se2_inverse, se2_relative
from roco_env.schema import build

__all__ = ["GATES", "AlignmentResult", "Policy", "PolicyAdapter", "PolicyWrapper",
           "ReadsFiles", "StatelessPolicy", "act", "apply_correction", "as_policy",
           "check_aligner_base", "correction_action", "policy_input_files",
           "reported_relative_poses"]

# policies that keep or reject collaborators behind a base aligner: none can be a base
GATES = ("defend", "privileged_gate", "reject_untested")


def check_aligner_base(policy: str, base: str) -> None:
    """Raise ValueError naming ``policy`` when ``base`` (a policy spec) is empty or one of
    :data:`GATES` rather than an aligner."""
    if not base or base.split(":")[0] in GATES:
        raise ValueError(f"{policy}: base must be the policy spec of an aligner (e.g. "
                         f"'roco'); got {base!r}")


@dataclass
class AlignmentResult:
    """Output of an alignment algorithm for one ego and N collaborator slots.

    corrected: (N, 3) corrected relative poses T_{j->i} (x m, y m, yaw rad).
    applied: (N,) bool, True where a correction was applied (False = prior kept).
    matched_pairs: (P, 4) int rows (slot_a, box_a, slot_b, box_b) saying box
        ``box_a`` of agent ``slot_a`` and box ``box_b`` of ``slot_b`` were judged the
        same object; slot -1 is the ego, 0..N-1 the collaborator slots.
    landmarks: (L, 3) landmark poses in the ego frame after optimisation.
    outer_iterations: matching/optimisation rounds; solver_iterations: LM iterations.
    reason: short text on why a prior was kept (empty when applied).
    slot_reasons: per collaborator slot, why its prior was kept, in full or along some
        directions ("" where applied in full or where the aligner does not say);
        ``reason`` is their readable summary.
    slot_statistics: per collaborator slot, the statistic of the aligner's do-no-harm
        significance test (chi-square with 3 dof when the reported pose is right; NaN
        where it was not computed); empty for an aligner without such a test.
    """

    corrected: np.ndarray
    applied: np.ndarray
    matched_pairs: np.ndarray = field(default_factory=lambda: np.zeros((0, 4), dtype=np.int64))
    landmarks: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    outer_iterations: int = 0
    solver_iterations: int = 0
    reason: str = ""
    slot_reasons: tuple[str, ...] = ()
    slot_statistics: tuple[float, ...] = ()


def reported_relative_poses(observation: dict) -> np.ndarray:
    """T_reported_{j->i} (N, 3) from an observation's own and collaborators' noisy poses.

    Empty slots (collab_mask 0) get the identity.
    """
    own = np.asarray(observation["pose"], dtype=float)
    others = np.asarray(observation["collab_poses"], dtype=float)
    rel = se2_relative(own[None, :], others)
    rel[np.asarray(observation["collab_mask"]) == 0] = 0.0
    return rel


def correction_action(reported: np.ndarray, corrected: np.ndarray) -> np.ndarray:
    """The action (N, 3) that turns reported relative poses into corrected ones."""
    return se2_compose(np.asarray(corrected, dtype=float), se2_inverse(reported)).astype(np.float32)


@runtime_checkable
class ReadsFiles(Protocol):
    """A policy that reads files declares them: ``input_files()`` returns every file (or
    folder: all files under it) whose content its actions depend on, e.g. its weights.
    A sweep hashes their content into each record's provenance, so overwriting one
    (retraining) makes the records of that policy stale instead of silently reused."""

    def input_files(self) -> Sequence[str | os.PathLike]:
        ...


def policy_input_files(policy: Any) -> tuple[Path, ...]:
    """The files ``policy`` declares through :class:`ReadsFiles` (none without the hook).

    Raises TypeError naming the policy when ``input_files()`` returns anything but a
    sequence of paths."""
    if not isinstance(policy, ReadsFiles):
        return ()
    declared = policy.input_files()
    if isinstance(declared, (str, os.PathLike)) or not isinstance(declared, Sequence) or \
            not all(isinstance(item, (str, os.PathLike)) for item in declared):
        raise TypeError(f"{type(policy).__name__}.input_files() must return a list of paths; "
                        f"got {declared!r}")
    return tuple(Path(item) for item in declared)


@runtime_checkable
class Policy(Protocol):
    """What the env's action modes, its wrappers, the episode loop and the sweeps call.

    ``__call__(observation, info=None)``: the action on one agent's observation (``info``
    is the env's info returned with it). ``reset()``: a new episode (forget what was kept).
    ``keeps_state``: falsy for a policy whose action depends on this call alone, else a
    text saying what it keeps across calls (``roco-env list`` shows it; the env's action
    modes run a stateful aligner on every step). ``last_result``: the
    :class:`AlignmentResult` of its last call, None when it reports none.
    """

    keeps_state: bool | str
    last_result: AlignmentResult | None

    def __call__(self, observation: Mapping[str, Any],
                 info: Mapping[str, Any] | None = None) -> np.ndarray:
        ...

    def reset(self) -> None:
        ...


class StatelessPolicy:
    """The :class:`Policy` members of a policy that keeps nothing across calls and reports
    no alignment result; subclasses define ``__call__``."""

    keeps_state: bool | str = False
    last_result: AlignmentResult | None = None

    def reset(self) -> None:
        """Nothing to forget."""


class PolicyAdapter:
    """A callable ``policy(observation, info=None) -> action`` as a :class:`Policy`: the
    members it has are its own, the missing ones the defaults (stateless, no result,
    ``reset`` does nothing). The files it declares (:class:`ReadsFiles`) and its
    ``env_overrides`` stay visible; ``policy`` is the callable itself."""

    def __init__(self, policy: Callable[..., Any]) -> None:
        self.policy = policy

    def __call__(self, observation: Mapping[str, Any],
                 info: Mapping[str, Any] | None = None) -> np.ndarray:
        return self.policy(observation, info)

    @property
    def keeps_state(self) -> bool | str:
        return getattr(self.policy, "keeps_state", False)

    @property
    def last_result(self) -> AlignmentResult | None:
        return getattr(self.policy, "last_result", None)

    @property
    def env_overrides(self) -> Mapping[str, Any] | None:
        """The env modes the callable acts in (None: it declares none)."""
        return getattr(self.policy, "env_overrides", None)

    def reset(self) -> None:
        reset = getattr(self.policy, "reset", None)
        if callable(reset):
            reset()

    def input_files(self) -> tuple[Path, ...]:
        """The files the callable declares (none without the hook)."""
        return policy_input_files(self.policy)


class PolicyWrapper:
    """The plumbing of a policy run around an inner one (``TemporalSmoothing``,
    ``Compensate``): its own parameters, the inner policy, and the members it passes on.

    ``params``: the wrapper's checked parameters; ``policy``: the inner :class:`Policy`;
    ``last_result`` and ``input_files()`` are the inner policy's (a sweep scores its
    matching and hashes its files); ``reset()`` resets it (a subclass forgets its own
    state, then calls ``super().reset()``). Subclasses define ``__call__`` and
    ``keeps_state``.
    """

    def __init__(self, inner: str | Callable[..., Any], own: Any,
                 params: Mapping[str, Any]) -> None:
        """inner: a policy name for ``make_policy`` (built with ``params``) or a callable
        (then ``params`` must be empty); own: the wrapper's parameters, checked
        (:func:`own_params`)."""
        if isinstance(inner, str):
            from roco_env.policies import make_policy

            inner = make_policy(inner, **params)
        elif params:
            raise ValueError(f"policy_params ({sorted(params)}: not parameters of the "
                             "wrapper) are only accepted with a policy name")
        self.params = own
        self.policy: Policy = as_policy(inner)

    @staticmethod
    def own_params(cls: type, params: Mapping[str, Any], where: str) -> tuple[Any, dict]:
        """(the fields of dataclass ``cls`` in ``params``, checked by
        :func:`~roco_env.schema.build` naming ``where``; the other parameters)."""
        own = {key: value for key, value in params.items() if key in cls.__dataclass_fields__}
        rest = {key: value for key, value in params.items() if key not in own}
        return build(cls, own, where), rest

    @property
    def last_result(self) -> AlignmentResult | None:
        """The inner policy's last AlignmentResult (None if it keeps none)."""
        return self.policy.last_result

    def input_files(self) -> tuple[Path, ...]:
        """The files the inner policy declares (:class:`ReadsFiles`), so a sweep's resume
        check still covers them once the policy is wrapped."""
        return policy_input_files(self.policy)

    def reset(self) -> None:
        """Reset the inner policy (a new episode)."""
        self.policy.reset()


def as_policy(policy: Any, label: str = "policy") -> Policy:
    """``policy`` itself when it is a :class:`Policy`, else the callable in a
    :class:`PolicyAdapter`; ValueError naming ``label`` when it is not callable."""
    if isinstance(policy, Policy):
        return policy
    if not callable(policy):
        raise ValueError(f"{label} must be a policy(obs, info) -> action; got {policy!r}")
    return PolicyAdapter(policy)


def act(policy: Policy, observation: Mapping[str, Any],
        info: Mapping[str, Any] | None) -> tuple[Any, AlignmentResult | None]:
    """(action, result) of one call of ``policy``: the action as returned (the env checks
    it) and the :class:`AlignmentResult` of this very call, None when the call reported
    none (a result left from an earlier call is never returned)."""
    previous = policy.last_result
    action = policy(observation, info)
    result = policy.last_result
    return action, None if result is previous else result
