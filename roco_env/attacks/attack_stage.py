"""What every attack shares: who attacks, the per-step context and the message rewrite.

An attack picks its attackers once per episode (:meth:`Attack.reset`): the agent ids of
``attack.agents``, or ``attack.count`` agents drawn from the attack's own child stream of
the episode seed (so adding an attack never changes the traffic, noise or detections of
an episode, and ``attack.kind: none`` leaves every episode bit-identical). Each step
:meth:`Attack.tamper` rewrites every message an attacker sends an honest ego (its
victim): its reported world pose (x m, y m, yaw rad) and its boxes (K, 7) in the
attacker's own sensor frame. Attackers collude: what they send each other, the ego's own
view and every honest agent's message stay as they are.

The truth about who attacks is privileged: :func:`attack_truth` is what the env puts in
``info["privileged"]``; no message or observation carries it. A rewritten message keeps
the privileged object ids of its boxes beside it (-1 for an injected box).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from roco_env.observation import top_k
from roco_env.scenario import AttackConfig, ScenarioConfig
from roco_env.schema import ConfigError
from roco_env.sensing.detector import AgentDetections
from roco_env.sensing.messages import Message
from roco_env.traffic.state import WorldState

__all__ = ["Attack", "NoAttack", "StepContext", "attack_truth", "attacker_indices"]

# One message's privileged object ids (K,) int64, -1 for a false positive or injected box.
ObjectIds = np.ndarray


@dataclass(frozen=True)
class StepContext:
    """What an attacker may use at one step (the worst case: it knows what its victims see).

    state: the world; detections: every agent's detections (true sensor frames, with their
    true object ids); own: (A, 3) the world pose each ego's view holds as its own (what a
    victim moves the attacker's boxes with); elapsed: seconds since the episode's first
    frame; max_boxes: K, the most boxes a message carries.
    """

    state: WorldState
    detections: tuple[AgentDetections, ...]
    own: np.ndarray
    elapsed: float
    max_boxes: int


class Attack:
    """Base of the attacks. Subclasses implement :meth:`forge` and may draw per episode in
    :meth:`start` and per step in :meth:`prepare` (from the attack's own stream)."""

    def __init__(self, config: ScenarioConfig, agent_ids: Sequence[str]) -> None:
        self.agent_ids = tuple(agent_ids)
        self.max_boxes = int(config.max_boxes)
        self._fixed = attacker_indices(config.attack, self.agent_ids)
        self._count = int(config.attack.count)
        # how many agents attack in every episode
        self.n_attackers = self._count if self._fixed is None else len(self._fixed)
        self.attackers: tuple[int, ...] = ()
        self.rng: np.random.Generator | None = None
        self._first_time: float | None = None

    def reset(self, rng: np.random.Generator) -> None:
        """A new episode: this episode's attackers, then :meth:`start`'s draws."""
        self.rng = rng
        self.attackers = self._fixed if self._fixed is not None else tuple(sorted(
            rng.choice(len(self.agent_ids), size=self._count, replace=False).tolist()))
        self._first_time = None
        self.start(rng)

    def start(self, rng: np.random.Generator) -> None:
        """Per-episode draws of the attack (none by default)."""

    def prepare(self, step: StepContext) -> None:
        """Per-step draws shared by every victim of an attacker (none by default)."""

    def forge(self, step: StepContext, victim: int, attacker: int, message: Message,
              ids: ObjectIds) -> tuple[Message, ObjectIds]:
        """The message ``attacker`` sends ``victim`` instead of ``message`` (agent indices),
        with the object ids of its boxes."""
        raise NotImplementedError

    def tamper(self, state: WorldState, detections: Sequence[AgentDetections],
               own: np.ndarray, messages: Sequence[Sequence[Message]],
               ids: Sequence[Sequence[ObjectIds]] | None = None
               ) -> tuple[list[list[Message]], list[list[ObjectIds]]]:
        """(messages, ids): per ego, the messages it receives (in order) and their boxes'
        object ids, every attacker's message to an honest ego rewritten by :meth:`forge`.
        ``ids``: the received boxes' object ids (a late message's are not the sender's
        current ones); None: the senders' current detections'."""
        index = {agent: k for k, agent in enumerate(self.agent_ids)}
        ids = [list(row) for row in ids] if ids is not None else \
            [[detections[index[m.sender]].object_ids for m in sent] for sent in messages]
        out = [list(sent) for sent in messages]
        if not self.attackers:
            return out, ids
        if self._first_time is None:
            self._first_time = float(state.time)
        step = StepContext(state, tuple(detections), np.asarray(own, dtype=float),
                           float(state.time) - self._first_time, self.max_boxes)
        self.prepare(step)
        for victim, sent in enumerate(out):
            if victim in self.attackers:
                continue
            for slot, message in enumerate(sent):
                sender = index[message.sender]
                if sender in self.attackers:
                    sent[slot], ids[victim][slot] = self.forge(step, victim, sender, message,
                                                               ids[victim][slot])
        return out, ids


class NoAttack(Attack):
    """``attack.kind: none``: every message as sent (``attack.agents`` is not read)."""

    def __init__(self, config: ScenarioConfig, agent_ids: Sequence[str]) -> None:
        self.agent_ids = tuple(agent_ids)
        self.max_boxes = int(config.max_boxes)
        self.n_attackers = 0
        self.attackers = ()

    def reset(self, rng: np.random.Generator) -> None:
        """Nothing to draw: no agent attacks."""


def attacker_indices(config: AttackConfig, agent_ids: Sequence[str]) -> tuple[int, ...] | None:
    """The indices of ``attack.agents`` (sorted), None when they are drawn per episode;
    a ConfigError naming the field for an id that is not an agent, a repeated id, every
    agent attacking, or a ``count`` that leaves no agent honest."""
    agents = list(agent_ids)
    if not config.agents:
        if config.count >= len(agents):
            raise ConfigError(f"attack.count={config.count} would make every one of the "
                              f"{len(agents)} agents an attacker; allowed 1..{len(agents) - 1}"
                              " (at least one agent must be honest)")
        return None
    unknown = [a for a in config.agents if a not in agents]
    if unknown:
        raise ConfigError(f"attack.agents: {unknown[0]!r} is not an agent of this env; "
                          f"choose among {agents}")
    if len(set(config.agents)) != len(config.agents):
        raise ConfigError(f"attack.agents names an agent twice: {config.agents!r}")
    if len(config.agents) >= len(agents):
        raise ConfigError(f"attack.agents names every agent ({config.agents!r}); at least one "
                          "agent must be honest")
    return tuple(sorted(agents.index(a) for a in config.agents))


def attack_truth(attackers: Sequence[int], agent: int, collaborators: Sequence[int],
                 max_collaborators: int) -> dict[str, np.ndarray | bool]:
    """The privileged truth about attackers in one observation: ``attacker`` (whether the
    agent itself attacks) and ``collab_attackers`` (N,) bool by collaborator slot (False for
    empty slots)."""
    slots = np.zeros(max_collaborators, dtype=bool)
    slots[: len(collaborators)] = np.isin(np.asarray(collaborators, dtype=np.int64),
                                          np.asarray(attackers, dtype=np.int64))
    return {"attacker": bool(agent in attackers), "collab_attackers": slots}


def rewritten(message: Message, ids: ObjectIds, max_boxes: int, *,
              pose: np.ndarray | None = None, boxes: np.ndarray | None = None,
              uncertainty: np.ndarray | None = None, scores: np.ndarray | None = None,
              keep: np.ndarray | None = None) -> tuple[Message, ObjectIds]:
    """``message`` with the given parts replaced, then only the ``keep`` rows (bool), then
    its ``max_boxes`` highest-scoring boxes (ties: earlier first, order kept)."""
    boxes = message.boxes if boxes is None else boxes
    uncertainty = message.uncertainty if uncertainty is None else uncertainty
    scores = message.scores if scores is None else scores
    rows = np.arange(scores.shape[0]) if keep is None else np.flatnonzero(keep)
    rows = rows[top_k(scores[rows], max_boxes)]
    new = dataclasses.replace(
        message, reported_pose=message.reported_pose if pose is None else np.asarray(pose),
        boxes=boxes[rows], uncertainty=uncertainty[rows], scores=scores[rows])
    return new, np.asarray(ids)[rows]
