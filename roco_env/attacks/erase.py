"""``erase``: the attacker withholds true detections from what it sends.

Withheld each step: every detection of an object in ``objects`` (true object ids), and of
the rest a share ``share``, drawn per detection each step from the attack's stream (one
draw per attacker, the same for all its victims). With ``hidden_only: true`` an attacker
withholds from a victim only the objects that victim does not detect itself, the ones it
cannot make up for (the worst case: the attacker knows what its victims see). What is
withheld is decided by object: a message the network delivers late loses the same
objects (its false positives are never withheld).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from roco_env.attacks.attack_stage import Attack, ObjectIds, StepContext, rewritten
from roco_env.scenario import ScenarioConfig
from roco_env.schema import ConfigError, build, spec
from roco_env.sensing.messages import Message

__all__ = ["Erase", "EraseParams"]


@dataclass
class EraseParams:
    """``erase``: which true detections the attacker withholds."""

    share: float = spec(0.5, low=0.0, high=1.0,
                        doc="share of its other detections withheld, drawn each step")
    objects: list = spec([], doc="true object ids always withheld when detected")
    hidden_only: bool = spec(False, doc="withhold from a victim only what it does not "
                             "detect itself")


class Erase(Attack):
    """See the module docstring; parameters :class:`EraseParams`."""

    def __init__(self, config: ScenarioConfig, agent_ids: Sequence[str]) -> None:
        super().__init__(config, agent_ids)
        self.params = build(EraseParams, config.attack.params, "attack", "attack.params.")
        if not all(isinstance(i, int) and not isinstance(i, bool) for i in self.params.objects):
            raise ConfigError(f"attack: attack.params.objects must be a list of integer object "
                              f"ids; got {self.params.objects!r}")
        self._objects = np.asarray(self.params.objects, dtype=np.int64)
        self._withheld: dict[int, np.ndarray] = {}

    def prepare(self, step: StepContext) -> None:
        """Each attacker's withheld objects this step (their ids: a message the network
        delivers late holds other rows than the attacker's current detections)."""
        self._withheld = {}
        for attacker in self.attackers:
            ids = step.detections[attacker].object_ids
            drawn = self.rng.random(ids.shape[0]) < self.params.share
            self._withheld[attacker] = np.union1d(ids[drawn & (ids >= 0)], self._objects)

    def forge(self, step: StepContext, victim: int, attacker: int, message: Message,
              ids: ObjectIds) -> tuple[Message, ObjectIds]:
        withheld = np.isin(ids, self._withheld[attacker]) & (ids >= 0)
        if self.params.hidden_only:
            withheld = withheld & ~(np.isin(ids, step.detections[victim].object_ids) & (ids >= 0))
        return rewritten(message, ids, step.max_boxes, keep=~withheld)
