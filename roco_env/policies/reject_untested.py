"""``reject_untested``: leave out the collaborators the aligner could not check.

``make_policy("reject_untested", base="roco_antialias")`` (spec
``reject_untested:base=roco_antialias``) acts in the env's ``select`` action mode with
``base`` as the one choice and the ``aligned`` observation (it declares these in
:attr:`RejectUntested.env_overrides`): per slot 0 takes the base aligner's pose, 1 rejects
the collaborator. It rejects every filled slot for which the base aligner computed no
do-no-harm statistic (``diagnostics`` column ``statistic`` = -1): it found no boxes
shared with the ego to test that collaborator's reported pose by, so the pose it fuses
with is unchecked. The kept collaborators keep the poses the aligner solved with every
collaborator; the gate mode would solve them again without the rejected ones, which on
the mixed benchmark costs 0.009 AP@0.7 at v2xset_like 3.0 (an untested collaborator's
boxes still tie the others together). It is the rule ``learned_select``'s guard applies.
``base`` must be an aligner that computes that statistic (roco, roco_antialias and
policies built on them): behind identity, coalign or the oracle every slot is untested,
so every collaborator is rejected (no fusion).

``tested`` and ``untested`` (policy specs, or ``"reject"`` for ``untested``) generalise
the rule to a choice per kind of slot: ``tested`` (default: ``base``) poses the slots the
base aligner tested, ``untested`` (default ``"reject"``) the others, e.g.
``reject_untested:untested=roco_fallback`` keeps roco_antialias where it tested and takes
roco_fallback's prior-free recovery elsewhere. The env's ``action.choices`` are then
``base`` followed by the other specs named (each run as the env's own aligner, every
step); the diagnostics that decide are ``base``'s. ``tested_within_m`` (m; with two
choices, ``tested`` other than ``base``) gives a tested slot ``tested``'s pose only where
it lies within that distance of ``base``'s (``choice_diagnostics`` column ``gap_m``), else
``base``'s: e.g. roco_fallback's second RoCo pass refines roco_antialias's poses by
centimetres, while on a parking lot roco's alias lies a stall (2.5 m) away from
roco_antialias's pose.

Why it pays: behind roco_antialias, from noise 0.8 m/deg up, 232 of 241 such slots lie
more than 1 m / 1 deg from the truth, against at most 5 of 1,000-2,000 tested slots per
condition (training seeds 1,000,000-1,000,009, ``baselines/learned_select/slot_errors.py``);
at low noise an untested slot is close to right and costs little to drop, because the
ego cannot confirm its boxes either. Measured on the mixed benchmark in
``baselines/learned_select/README.md``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from roco_env.policies.base import StatelessPolicy
from roco_env.policies.landmarks import params_from_kwargs
from roco_env.schema import spec

__all__ = ["RejectUntested", "RejectUntestedParams", "tested_choice", "untested_slots"]

# column "statistic" of roco_env.observation_modes.DIAGNOSTICS (a higher layer;
# tests/test_reject_untested.py checks the index) and its value where none was computed
STATISTIC, NO_STATISTIC = 3, -1.0
REJECT = "reject"  # reject_untested's ``untested`` value that leaves the slot out
GAP_M = 7  # column "gap_m" of roco_env.observation_modes.CHOICE_DIAGNOSTICS (checked too)
GAP_CLIP_M = 20.0  # the observation clips gap_m to [0, this] (observation_modes.py)
def tested_choice(choice_diagnostics: np.ndarray, keep: int, prefer: int | None,
                  within_m: float | None) -> np.ndarray:
    """(N,) int64: the choice a tested slot takes: ``keep``; or ``prefer`` where that
    choice's ``gap_m`` (m between its pose and ``keep``'s, column :data:`GAP_M` of the
    (N, C, D) ``choice_diagnostics``) is at most ``within_m`` (None: always)."""
    count = np.shape(choice_diagnostics)[0]
    if prefer is None or within_m is None:
        return np.full(count, keep if prefer is None else prefer, np.int64)
    gap = np.asarray(choice_diagnostics)[:, prefer, GAP_M]
    return np.where(gap <= within_m, prefer, keep).astype(np.int64)


def untested_slots(statistic: np.ndarray, collab_mask: np.ndarray) -> np.ndarray:
    """(N,) bool: the filled slots (``collab_mask`` > 0) whose aligner ``statistic``
    (N,) is :data:`NO_STATISTIC` (none computed)."""
    return (np.asarray(statistic) == NO_STATISTIC) & (np.asarray(collab_mask) > 0)


@dataclass(frozen=True)
class RejectUntestedParams:
    """``reject_untested``'s parameter (module docstring)."""

    base: str = spec("roco_antialias", doc="the aligner's policy spec the env runs "
                     "(action.base); one that computes a do-no-harm statistic (roco, "
                     "roco_antialias and their wrappers): behind one that computes none "
                     "(identity, coalign, oracle, ...) every collaborator is rejected")
    tested: str = spec("", doc="the aligner's policy spec whose pose the tested slots "
                       "take; empty: base")
    untested: str = spec(REJECT, doc="what the untested slots take: 'reject', or an "
                         "aligner's policy spec")
    tested_within_m: float | None = spec(None, low=0.0, high=GAP_CLIP_M,
                                         high_open=True, doc="m, in [0, 20) (the "
                                         "observation clips gap_m at 20 m, so 20 would "
                                         "mean always): "
                                         "a tested slot takes tested's pose only within "
                                         "this distance of base's (None: always); two "
                                         "choices only")

    def __post_init__(self) -> None:
        # lazy: the spec module imports the registry (and the scenario layer)
        from roco_env.policies.spec import ALIGNER, check_aligner_spec

        check_aligner_spec("reject_untested", "base", self.base)
        if self.tested == REJECT:
            raise ValueError(f"reject_untested: tested must be {ALIGNER} (empty: base); got "
                             f"{self.tested!r}")
        if self.tested:
            check_aligner_spec("reject_untested", "tested", self.tested)
        if self.untested != REJECT:
            check_aligner_spec("reject_untested", "untested (or 'reject')", self.untested)
        if self.tested_within_m is not None and (
                len(self.choices) != 2 or self.tested in ("", self.base)):
            raise ValueError("reject_untested: tested_within_m needs tested other than "
                             f"base and two choices in all; got choices {self.choices}")

    @property
    def choices(self) -> list[str]:
        """The env's ``action.choices``: ``base``, then ``tested`` and ``untested`` where
        they name other aligners."""
        named = [self.base, self.tested or self.base, self.untested]
        return list(dict.fromkeys(c for c in named if c != REJECT))


class RejectUntested(StatelessPolicy):
    """``RejectUntested(base="roco_antialias")(obs, info) -> (N,) int64`` select action: by
    default 1 (reject) for the filled slots the base aligner left untested, else 0 (its
    pose); with ``tested`` / ``untested`` the indices of those choices in
    :attr:`RejectUntestedParams.choices` (reject = their count). It reports no alignment
    of its own (the env's aligners align)."""

    def __init__(self, **params: Any) -> None:
        self.params = params_from_kwargs(RejectUntestedParams, params, "reject_untested")
        choices = self.params.choices
        self._tested = choices.index(self.params.tested or self.params.base)
        self._untested = (len(choices) if self.params.untested == REJECT
                          else choices.index(self.params.untested))
        self.env_overrides = {"action.mode": "select", "action.choices": choices,
                              "action.base": self.params.base, "observation.mode": "aligned"}

    def __call__(self, observation: Mapping[str, Any], info: Mapping | None = None
                 ) -> np.ndarray:
        if "diagnostics" not in observation:
            raise ValueError("reject_untested reads the aligned observation's diagnostics: "
                             "run the env with observation.mode='aligned' (its "
                             "env_overrides; sweeps and EgoEnv merge them)")
        statistic = np.asarray(observation["diagnostics"])[:, STATISTIC]
        untested = untested_slots(statistic, observation["collab_mask"])
        tested = np.full(len(untested), self._tested)
        if self.params.tested_within_m is not None:
            tested = tested_choice(observation["choice_diagnostics"], 0, self._tested,
                                   self.params.tested_within_m)
        return np.where(untested, self._untested, tested).astype(np.int64)
