"""What every alignment policy shares: the result type and observation helpers.

A policy is any callable ``policy(observation, info=None) -> action`` where the
action (N, 3) holds one correction (dx, dy, dyaw) per collaborator slot, in the
ego frame: ``T_corrected_{j->i} = SE2(dx, dy, dyaw) * T_reported_{j->i}``
(metres, radians). Zeros trust the reported poses. Built-in alignment policies
also keep their last :class:`AlignmentResult` in ``policy.last_result`` so a
sweep can score their matching. A policy that reads files (learned weights, lookup
tables) declares them with an ``input_files()`` method (:class:`ReadsFiles`), so a
sweep's resume check covers their content.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from roco_env.geometry import apply_correction, se2_compose, se2_inverse, se2_relative

__all__ = ["AlignmentResult", "ReadsFiles", "apply_correction", "correction_action",
           "policy_input_files", "reported_relative_poses"]


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
