"""Observation adapter shared by the array-based aligners (CoAlign, RoCo).

Maps one agent's env observation (contract layout: padded slots with masks) to
the array call ``align(ego_boxes, ego_unc, collab_boxes, collab_unc, reported,
**params)``: only masked boxes are used, collaborator boxes stay in their own
frames, reported relative poses come from ``obs["collab_rel_poses"]`` of the
filled slots. The result is mapped back to slot and box positions of the
observation, and the action is the correction that turns the reported relative
poses into the corrected ones (zeros for empty slots).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from roco_env.policies.base import AlignmentResult, correction_action

__all__ = ["ArrayAlignmentPolicy", "ObservationView", "collaborator_keys", "unpack_observation"]

_KEYS = (
    "boxes",
    "uncertainty",
    "box_mask",
    "collab_mask",
    "collab_rel_poses",
    "collab_boxes",
    "collab_uncertainty",
    "collab_box_mask",
)


@dataclass(frozen=True)
class ObservationView:
    """The filled part of an observation.

    slots (n,): filled collaborator slots; ego_index (K0,), collab_index[j] (K_j,):
    positions of the used boxes in the padded arrays; reported_full (N, 3): reported
    T_{j->i} for every slot (identity where empty).
    """

    ego_boxes: np.ndarray
    ego_unc: np.ndarray
    ego_index: np.ndarray
    collab_boxes: list[np.ndarray]
    collab_unc: list[np.ndarray]
    collab_index: list[np.ndarray]
    slots: np.ndarray
    reported_full: np.ndarray

    @property
    def reported(self) -> np.ndarray:
        return self.reported_full[self.slots]

    @property
    def arrays(self) -> tuple:
        """The positional arguments of an array aligner: (ego_boxes, ego_unc,
        collab_boxes, collab_unc, reported)."""
        return self.ego_boxes, self.ego_unc, self.collab_boxes, self.collab_unc, self.reported

    def expand(self, result: AlignmentResult) -> AlignmentResult:
        """Map a result over the filled slots/used boxes back to observation positions."""
        n = self.reported_full.shape[0]
        corrected = self.reported_full.copy()
        corrected[self.slots] = result.corrected
        applied = np.zeros(n, dtype=bool)
        applied[self.slots] = result.applied
        pairs = np.asarray(result.matched_pairs, dtype=np.int64).reshape(-1, 4).copy()
        # Box k of compact slot c (-1 = ego) sits at box_index[start[c + 1] + k].
        box_index = np.concatenate([self.ego_index, *self.collab_index]).astype(np.int64)
        start = np.cumsum([0, self.ego_index.size, *(i.size for i in self.collab_index)])
        slot_of = np.concatenate([[-1], self.slots]).astype(np.int64)
        for col in (0, 2):
            compact = pairs[:, col] + 1
            pairs[:, col + 1] = box_index[start[compact] + pairs[:, col + 1]]
            pairs[:, col] = slot_of[compact]
        reasons = [""] * n
        for compact, text in enumerate(result.slot_reasons):
            reasons[self.slots[compact]] = text
        statistics = ()
        if result.slot_statistics:
            full = np.full(n, np.nan)
            full[self.slots] = result.slot_statistics
            statistics = tuple(full.tolist())
        return replace(result, corrected=corrected, applied=applied, matched_pairs=pairs,
                       slot_reasons=tuple(reasons), slot_statistics=statistics)


def collaborator_keys(info: dict | None, slots: Sequence[int], policy: str) -> list[tuple]:
    """The key of each filled collaborator slot for state kept across steps: (ego id,
    collaborator id) from ``info["agent"]`` and ``info["collaborators"]``, so reordered
    slots keep their state and one instance serving several egos never mixes theirs.

    ValueError naming ``policy`` (the stateful policy) when the info lacks either id:
    keyed by slot, the egos sharing an instance would share (and corrupt) one state.
    """
    info = {} if info is None else info
    ego, names = info.get("agent"), info.get("collaborators")
    if ego is None or names is None:
        raise ValueError(
            f"{policy} keeps state per ego and collaborator, so it needs the env's info with "
            "'agent' and 'collaborators': call policy(obs[agent], infos[agent]); got "
            f"{'no info' if not info else 'an info with keys ' + str(sorted(info))}")
    unnamed = [int(s) for s in slots if s >= len(names) or names[s] is None]
    if unnamed:
        raise ValueError(f"{policy}: info['collaborators'] ({len(names)} names) names no "
                         f"agent for the filled collaborator slots {unnamed}")
    return [(ego, names[s]) for s in slots]


def _field(observation: dict, key: str) -> np.ndarray:
    if key not in observation:
        raise ValueError(f"observation lacks {key!r}; required keys: {', '.join(_KEYS)}")
    return np.asarray(observation[key])


def unpack_observation(observation: dict) -> ObservationView:
    """Extract the masked boxes and filled slots of one agent's observation."""
    boxes, unc = _field(observation, "boxes"), _field(observation, "uncertainty")
    ego_index = np.nonzero(_field(observation, "box_mask") > 0)[0]
    collab_mask = _field(observation, "collab_mask") > 0
    rel = np.asarray(_field(observation, "collab_rel_poses"), dtype=float).reshape(-1, 3)
    cboxes, cunc = _field(observation, "collab_boxes"), _field(observation, "collab_uncertainty")
    cmask = _field(observation, "collab_box_mask") > 0
    slots = np.nonzero(collab_mask)[0]
    reported_full = np.where(collab_mask[:, None], rel, 0.0)
    collab_index = [np.nonzero(cmask[s])[0] for s in slots]
    return ObservationView(
        ego_boxes=np.asarray(boxes[ego_index], dtype=float),
        ego_unc=np.asarray(unc[ego_index], dtype=float),
        ego_index=ego_index,
        collab_boxes=[
            np.asarray(cboxes[s][i], dtype=float) for s, i in zip(slots, collab_index, strict=True)
        ],
        collab_unc=[
            np.asarray(cunc[s][i], dtype=float) for s, i in zip(slots, collab_index, strict=True)
        ],
        collab_index=collab_index,
        slots=slots,
        reported_full=reported_full,
    )


class ArrayAlignmentPolicy:
    """Env policy around an array aligner ``align(...) -> AlignmentResult``.

    ``params`` (already validated by the subclass) is kept as ``self.params``; the raw
    keyword arguments are passed to ``align`` on every call. ``self.last_result`` holds
    the last result in observation positions (slots, box indices). Subclasses that need
    more per call (arguments from the observation or the info dict, state across calls)
    override :meth:`align_view`, the one step between unpacking the observation and
    mapping the result back; one that keeps state says what in ``keeps_state``
    (:class:`~roco_env.policies.base.Policy`).
    """

    keeps_state: bool | str = False

    def __init__(self, align: Callable[..., AlignmentResult], params: object, kwargs: dict):
        self._align = align
        self._kwargs = dict(kwargs)
        self.params = params
        self.last_result: AlignmentResult | None = None

    def align_view(
        self, view: ObservationView, observation: dict, info: dict | None
    ) -> AlignmentResult:
        """Align the filled part of one observation (result over the filled slots and
        used boxes, as the array aligner returns it)."""
        return self._align(*view.arrays, **self._kwargs)

    def __call__(self, observation: dict, info: dict | None = None) -> np.ndarray:
        view = unpack_observation(observation)
        self.last_result = view.expand(self.align_view(view, observation, info))
        return correction_action(view.reported_full, self.last_result.corrected)

    def reset(self) -> None:
        """Stateless between frames; kept for a uniform policy interface."""
        self.last_result = None
