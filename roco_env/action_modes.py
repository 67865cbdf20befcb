"""What an agent's action means: the modes of the scenario section ``action``.

Every mode turns one agent's action, taken on the observation it received last, into a
:class:`Decision`: the relative pose ``T_{j->i}`` (x m, y m, yaw rad, in the ego's frame)
each filled collaborator slot is fused with, and which slots are kept. A rejected
collaborator is left out of fusion (late and intermediate alike); the ground truth the
ego is scored against stays the collaboration's, so rejecting a useful collaborator costs
what it would have added. docs/learning.md describes the modes for RL users.

* ``correction`` (default): a Box (N, 3) of corrections (dx m, dy m, dyaw rad),
  ``T = SE2(action) * T_reported``; bounds ``action.max_translation`` m and
  ``action.max_rotation`` degrees; finite values outside are applied as given.
* ``residual``: the base aligner (``action.base``) runs first; the action, a Box (N, 3)
  in [-1, 1] (values outside are clipped), is a residual scaled by ``action.scale``
  (m, m, degrees): ``T = SE2(scale * action) * T_base``. Zeros give the base aligner's
  poses exactly.
* ``select``: a MultiDiscrete (N,) of indices: ``k < len(action.choices)`` fuses the slot
  with the pose the k-th choice computes, ``len(action.choices)`` rejects it.
* ``gate``: a MultiDiscrete (N,) of 0 (keep the base aligner's pose) or 1 (reject). When
  a slot is rejected, the base aligner runs again without the rejected collaborators
  (once per agent and step), so a rejected collaborator influences no kept one's pose
  (a joint aligner such as roco's pose graph would otherwise let its boxes pull on them).

The aligners a mode names run inside the env, one instance per agent (several keep
state per ego), on the same (raw) observation and info the agent received; the base
aligner runs when the env builds each observation (:class:`AlignerSet`), so the
``aligned`` observation shows the very poses the ``residual`` and ``gate`` actions act on.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from gymnasium import spaces

from roco_env.geometry import apply_correction
from roco_env.observation import EgoView, action_space, check_action
from roco_env.scenario import ActionConfig

if TYPE_CHECKING:  # the policies load when a mode names one: `import roco_env` stays light
    from roco_env.policies.base import AlignmentResult, Policy
    from roco_env.policies.spec import PolicySpec

REJECT_GATE = 1  # gate mode's "reject"; 0 keeps the base aligner's pose


@dataclass(frozen=True)
class Decision:
    """One agent's decision on its filled collaborator slots (n = len(view.collaborators)).

    corrected: (n, 3) relative poses ``T_{j->i}`` (x m, y m, yaw rad) fusion moves each
        collaborator's boxes or maps with; a rejected slot holds its reported pose (so its
        pose error after equals the one before).
    kept: (n,) bool, False where the collaborator is left out of fusion.
    """

    corrected: np.ndarray
    kept: np.ndarray


@dataclass(frozen=True)
class Alignment:
    """One aligner's output for one agent's filled slots.

    corrected: (n, 3) relative poses ``T_{j->i}`` it computed; result: its
    :class:`~roco_env.policies.base.AlignmentResult` for this call, or None when the
    policy reports none.
    """

    corrected: np.ndarray
    result: AlignmentResult | None


class AlignerSet:
    """One instance of each named policy per agent, called on the agent's raw observation.

    field: the scenario field naming the policies (errors name it); texts: their policy
    specs; agents: the env's agent ids.
    """

    def __init__(self, field: str, texts: Sequence[str], agents: Sequence[str]) -> None:
        self.specs = [_policy_spec(text, field) for text in texts]
        self.instances: dict[str, list[Policy]] = {
            agent: [spec.build() for spec in self.specs] for agent in agents}
        # whether each aligner must see every step (it keeps state), asked once
        self.stateful = [any(bool(instances[index].keeps_state)
                             for instances in self.instances.values())
                         for index in range(len(self.specs))]

    def reset(self) -> None:
        """A new episode for every instance (the stateful ones forget the last)."""
        for instances in self.instances.values():
            for policy in instances:
                policy.reset()

    def align(self, agent: str, index: int, view: EgoView, observation: dict,
              info: dict) -> Alignment:
        """What the ``index``-th aligner computes for ``agent``'s filled slots."""

        return self._run(self.instances[agent][index], agent, index, view, observation, info)

    def align_without(self, agent: str, index: int, view: EgoView, observation: dict,
                      info: dict, left_out: np.ndarray) -> Alignment:
        """What the ``index``-th aligner computes for ``agent``'s filled slots when the
        collaborators of the (n,) bool ``left_out`` are not there (their slots emptied in
        ``observation``; their poses come back reported). A stateful aligner runs on a copy
        of its instance: its state follows the step's first call only."""
        policy = self.instances[agent][index]
        if self.stateful[index]:
            policy = copy.deepcopy(policy)
        mask = np.array(observation["collab_mask"], copy=True)
        mask[: left_out.shape[0]][left_out] = 0
        alignment = self._run(policy, agent, index, view, {**observation, "collab_mask": mask},
                              info)
        alignment.corrected[left_out] = view.reported_relative[left_out]
        return alignment

    def _run(self, policy: Policy, agent: str, index: int, view: EgoView, observation: dict,
             info: dict) -> Alignment:
        from roco_env.policies.base import act

        action, result = act(policy, observation, info)
        action = check_action(action, f"{agent} ({self.specs[index].label})",
                              len(observation["collab_mask"]))
        n = len(view.collaborators)
        return Alignment(apply_correction(view.reported_relative, action[:n]), result)


class ActionMode:
    """Base of the modes: the action space, the action check and the decision.

    ``needs_base``: whether :meth:`decide` reads the base aligner's poses (``base``).
    :meth:`decide` gets the agent's info as a function (``info_of()``): building it costs
    a step's time, so only a mode that runs an aligner on this step builds it.
    """

    space: spaces.Space
    needs_base = False
    observed_choices = 0  # aligners whose alignments the aligned observation shows

    def reset(self) -> None:
        """Start an episode (stateful aligners forget the last one)."""

    def bind_base(self, base: AlignerSet | None) -> None:
        """The env's base aligner (None without one), for a mode that runs it again."""

    def observe(self, agent: str, view: EgoView, observation: dict,
                info: dict) -> list[Alignment]:
        """The alignments of ``agent``'s new observation the aligned observation shows, in
        order (``observed_choices`` of them)."""
        return []

    def choice_index(self, text: str) -> int | None:
        """The index of the observed choice that is the policy ``text`` (the env then takes
        the base aligner's alignment from it instead of running the same aligner twice);
        None where none is."""
        return None

    def neutral_action(self) -> np.ndarray:
        """The action that changes nothing the mode decides (zeros)."""
        return np.zeros(self.space.shape, dtype=self.space.dtype)

    def check(self, action: object, agent: str) -> np.ndarray:
        raise NotImplementedError

    def decide(self, agent: str, action: np.ndarray, view: EgoView, observation: dict,
               info_of: Callable[[], dict], base: np.ndarray | None) -> Decision:
        """The decision of ``action`` (checked) on ``agent``'s last observation; ``info_of()``
        builds the agent's info (for an aligner the mode runs); ``base`` holds the base
        aligner's (n, 3) poses when the mode needs them, else None."""
        raise NotImplementedError


class CorrectionMode(ActionMode):
    """The action is the correction itself (today's contract)."""

    def __init__(self, config: ActionConfig, max_collaborators: int) -> None:
        self.n = max_collaborators
        self.space = action_space(max_collaborators, config.max_translation,
                                  np.radians(config.max_rotation))

    def check(self, action: object, agent: str) -> np.ndarray:
        return check_action(action, agent, self.n)

    def decide(self, agent: str, action: np.ndarray, view: EgoView, observation: dict,
               info_of: Callable[[], dict], base: np.ndarray | None) -> Decision:
        n = len(view.collaborators)
        return Decision(apply_correction(view.reported_relative, action[:n]), np.ones(n, bool))


class ResidualMode(ActionMode):
    """A scaled residual on top of the base aligner's poses."""

    needs_base = True

    def __init__(self, config: ActionConfig, max_collaborators: int) -> None:
        self.n = max_collaborators
        self.scale = np.array([config.scale[0], config.scale[1], np.radians(config.scale[2])])
        self.space = spaces.Box(-1.0, 1.0, (max_collaborators, 3), np.float32)

    def check(self, action: object, agent: str) -> np.ndarray:
        return np.clip(check_action(action, agent, self.n), -1.0, 1.0)

    def decide(self, agent: str, action: np.ndarray, view: EgoView, observation: dict,
               info_of: Callable[[], dict], base: np.ndarray | None) -> Decision:
        n = len(view.collaborators)
        corrected = base.copy()
        residual = action[:n].astype(float) * self.scale
        moved = np.any(residual != 0.0, axis=1)  # a zero residual keeps the base pose exactly
        corrected[moved] = apply_correction(corrected[moved], residual[moved])
        return Decision(corrected, np.ones(n, bool))


class SelectMode(ActionMode):
    """Per slot, one of the choices' poses, or reject (index ``len(choices)``).

    With the ``aligned`` observation the env calls :meth:`observe` on every observation
    (its ``choice_diagnostics`` read every choice): the action then reuses those poses;
    otherwise a stateless choice runs only when a slot picks it.
    """

    def __init__(self, config: ActionConfig, max_collaborators: int,
                 agents: Sequence[str]) -> None:
        self.n = max_collaborators
        self.choices = AlignerSet("action.choices", config.choices, agents)
        self.reject = len(config.choices)
        self.observed_choices = self.reject
        self.space = spaces.MultiDiscrete(np.full(max_collaborators, self.reject + 1))
        self._observed: dict[str, list[Alignment]] = {}  # by agent: its last observation's

    def reset(self) -> None:
        self.choices.reset()
        self._observed = {}

    def check(self, action: object, agent: str) -> np.ndarray:
        return check_indices(action, agent, self.n, self.reject + 1)

    def observe(self, agent: str, view: EgoView, observation: dict,
                info: dict) -> list[Alignment]:
        """Every choice's alignment of ``agent``'s new observation, in order; kept for the
        action taken on it (each aligner runs once per observation)."""
        self._observed[agent] = [self.choices.align(agent, index, view, observation, info)
                                 for index in range(self.reject)]
        return self._observed[agent]

    def choice_index(self, text: str) -> int | None:
        spec = _policy_spec(text, "action.base")
        return self.choices.specs.index(spec) if spec in self.choices.specs else None

    def decide(self, agent: str, action: np.ndarray, view: EgoView, observation: dict,
               info_of: Callable[[], dict], base: np.ndarray | None) -> Decision:
        n = len(view.collaborators)
        picked = action[:n]
        corrected = view.reported_relative[:n].astype(float).copy()
        observed = self._observed.pop(agent, None)
        for index in range(self.reject):
            chosen = picked == index
            if observed is not None:
                corrected[chosen] = observed[index].corrected[chosen]
            # a stateless aligner nobody picked is not run; a stateful one sees every step
            elif chosen.any() or self.choices.stateful[index]:
                poses = self.choices.align(agent, index, view, observation,
                                           info_of()).corrected
                corrected[chosen] = poses[chosen]
        return Decision(corrected, picked != self.reject)


class GateMode(ActionMode):
    """Per slot, keep the base aligner's pose (0) or reject the collaborator (1); with a
    slot rejected, the kept slots take the base aligner's poses solved without the
    rejected collaborators (module docstring)."""

    needs_base = True

    def __init__(self, max_collaborators: int) -> None:
        self.n = max_collaborators
        self.space = spaces.MultiDiscrete(np.full(max_collaborators, 2))
        self.base: AlignerSet | None = None

    def bind_base(self, base: AlignerSet | None) -> None:
        self.base = base

    def check(self, action: object, agent: str) -> np.ndarray:
        return check_indices(action, agent, self.n, 2)

    def decide(self, agent: str, action: np.ndarray, view: EgoView, observation: dict,
               info_of: Callable[[], dict], base: np.ndarray | None) -> Decision:
        n = len(view.collaborators)
        kept = action[:n] != REJECT_GATE
        if kept.all():
            return Decision(base.copy(), kept)
        return Decision(self.base.align_without(agent, 0, view, observation, info_of(),
                                                ~kept).corrected, kept)


def build_action_mode(config: ActionConfig, max_collaborators: int,
                      agents: Sequence[str]) -> ActionMode:
    """The mode ``config.mode`` names, its aligners built for every agent.

    Raises ValueError naming ``action.base`` / ``action.choices`` for a policy spec that
    is unknown or whose parameters its policy refuses.
    """
    if config.mode == "residual":
        return ResidualMode(config, max_collaborators)
    if config.mode == "select":
        return SelectMode(config, max_collaborators, agents)
    if config.mode == "gate":
        return GateMode(max_collaborators)
    return CorrectionMode(config, max_collaborators)


def check_indices(action: object, agent: str, max_collaborators: int,
                  count: int) -> np.ndarray:
    """``action`` as an (N,) int64 array of indices in [0, count), else a ValueError naming
    the agent, the shape and the allowed values (bools, floats with a fraction, NaN refused)."""
    array = np.asarray(action)
    if array.shape != (max_collaborators,):
        raise ValueError(f"action of {agent!r} must have shape ({max_collaborators},), one "
                         f"index per collaborator slot; got shape {array.shape}")
    if array.dtype == bool or not (np.issubdtype(array.dtype, np.integer)
                                   or np.issubdtype(array.dtype, np.floating)):
        raise ValueError(f"action of {agent!r} must hold integer indices in [0, {count - 1}]; "
                         f"got dtype {array.dtype}")
    if not np.all(np.isfinite(array)) or np.any(array != np.round(array)) \
            or np.any(array < 0) or np.any(array >= count):
        raise ValueError(f"action of {agent!r} must hold integer indices in [0, {count - 1}]; "
                         f"got {array.tolist()}")
    return array.astype(np.int64)


def _policy_spec(text: object, field: str) -> PolicySpec:
    """The checked spec of ``text``, or a ValueError naming the scenario field."""
    from roco_env.policies.spec import validate_policy_spec

    if not isinstance(text, str):
        raise ValueError(f"{field} must be a policy spec such as 'roco' or "
                         f"'roco:tau2=2'; got {text!r}")
    try:
        return validate_policy_spec(text)
    except ValueError as exc:
        raise ValueError(f"{field}: {exc}") from exc
