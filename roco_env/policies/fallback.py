"""RoCo with a prior-free fallback: the answer for large pose noise (``roco_fallback``).

RoCo leans on the reported pose: its matching gates (``tau2``, the ``coarse_tau2``
fallback gate) are centred on it. Beyond a few metres / degrees of error it finds no
consistent matching and keeps the prior. This policy

1. runs :func:`~roco_env.policies.roco.roco_align` on the reported poses;
2. for every collaborator RoCo *kept at its prior for lack of evidence* (too few
   matches or inlier matches; a prior kept because the correction was not significant
   is a prior RoCo checked and found right, and is left alone), runs a prior-free
   aligner (``fallback``: ``"ransac"``, ``"v2i_calib"`` or ``"freealign"``, with its
   do-no-harm rule on);
3. takes the prior-free estimate only when it is *distinct* from the reported pose
   (farther than the fallback's ``distinct_distance`` m or ``distinct_yaw_deg`` deg):
   an estimate next to the prior says the prior was not far off, so RoCo's decision
   stands (this keeps the clean-pose case untouched);
4. re-runs RoCo with those estimates in place of the reported poses, so RoCo's
   matching and robust pose graph refine them (its prior edge now pulls towards the
   estimate). A collaborator RoCo then keeps at its (new) prior keeps the estimate.

Parameters: ``fallback`` names the aligner; keys prefixed ``fallback_`` go to it with
the prefix removed (e.g. ``fallback_min_inliers=4``); every other key goes to RoCo.
The result's ``applied`` is True where the final pose differs from the reported one;
``outer_iterations`` / ``solver_iterations`` add up both RoCo passes.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from roco_env.policies.base import AlignmentResult
from roco_env.policies.freealign import FreeAlignParams, freealign_align
from roco_env.policies.landmarks import params_from_kwargs
from roco_env.policies.observation import ArrayAlignmentPolicy
from roco_env.policies.prior_free import poses_distinct
from roco_env.policies.ransac import RansacParams, ransac_align
from roco_env.policies.roco import RoCoParams, roco_align
from roco_env.policies.v2i_calib import V2ICalibParams, v2i_calib_align

__all__ = ["FALLBACKS", "roco_fallback_align", "RoCoFallbackPolicy"]

FALLBACKS = {
    "ransac": (ransac_align, RansacParams),
    "v2i_calib": (v2i_calib_align, V2ICalibParams),
    "freealign": (freealign_align, FreeAlignParams),
}
_PREFIX = "fallback_"
# Prefix of RoCo's reason for a prior it kept because the evidence did not show it wrong.
_CHECKED_PRIOR = "correction not significant"


def _split(params: dict) -> tuple[str, dict, dict]:
    """(fallback name, its params, roco params), each validated."""
    params = dict(params)
    name = params.pop("fallback", "ransac")
    if name not in FALLBACKS:
        raise ValueError(f"fallback must be one of {sorted(FALLBACKS)}; got {name!r}")
    inner = {k[len(_PREFIX):]: v for k, v in params.items() if k.startswith(_PREFIX)}
    roco = {k: v for k, v in params.items() if not k.startswith(_PREFIX)}
    params_from_kwargs(FALLBACKS[name][1], inner, f"roco_fallback fallback {name!r}")
    params_from_kwargs(RoCoParams, roco, "roco_fallback")
    return name, inner, roco


def _slot_reasons(result: AlignmentResult) -> dict[int, str]:
    """RoCo's per-slot reasons ("slot j: why; slot k: why")."""
    reasons = {}
    for part in result.reason.split("; "):
        head, _, text = part.partition(": ")
        if head.startswith("slot ") and head[5:].isdigit():
            reasons[int(head[5:])] = text
    return reasons


def roco_fallback_align(
    ego_boxes: np.ndarray,
    ego_unc: np.ndarray,
    collab_boxes: Sequence[np.ndarray],
    collab_unc: Sequence[np.ndarray],
    reported: np.ndarray,
    **params,
) -> AlignmentResult:
    """RoCo, with a prior-free aligner where RoCo finds no evidence (module docstring).

    Same array call as :func:`roco_env.policies.roco.roco_align`.
    """
    name, inner, roco_params = _split(params)
    reported = np.asarray(reported, dtype=float)
    first = roco_align(ego_boxes, ego_unc, collab_boxes, collab_unc, reported, **roco_params)
    reasons = _slot_reasons(first)
    stuck = [j for j in range(first.applied.size)
             if not first.applied[j] and len(collab_boxes[j])
             and not reasons.get(j, "").startswith(_CHECKED_PRIOR)]
    if not stuck:
        return first
    align, params_cls = FALLBACKS[name]
    inner.setdefault("do_no_harm", True)
    fallback_params = params_from_kwargs(params_cls, inner, name)
    estimate = align(ego_boxes, ego_unc, [collab_boxes[j] for j in stuck],
                     [collab_unc[j] for j in stuck], reported[stuck], **inner)
    far = poses_distinct(estimate.corrected, reported[stuck], fallback_params)
    use = np.array(stuck)[estimate.applied & far]
    if use.size == 0:
        return first
    prior = reported.copy()
    prior[use] = estimate.corrected[np.searchsorted(stuck, use)]
    second = roco_align(ego_boxes, ego_unc, collab_boxes, collab_unc, prior, **roco_params)
    applied = second.applied.copy()
    applied[use] = True
    # Slots RoCo's second pass kept at the estimate: report the fallback's matches.
    sub = estimate.matched_pairs
    sub_slots = np.array(stuck)[sub[:, 2]]
    extra = sub[np.isin(sub_slots, use) & ~second.applied[sub_slots]].copy()
    extra[:, 2] = np.array(stuck)[extra[:, 2]]
    note = f"slots {use.tolist()}: re-localised by {name}, then refined by roco"
    return replace(
        second,
        applied=applied,
        outer_iterations=first.outer_iterations + second.outer_iterations,
        solver_iterations=first.solver_iterations + second.solver_iterations,
        matched_pairs=np.concatenate([second.matched_pairs, extra]),
        reason="; ".join(r for r in (second.reason, note) if r),
    )


class RoCoFallbackPolicy(ArrayAlignmentPolicy):
    """``roco_fallback`` as an env policy: ``RoCoFallbackPolicy(**params)(obs) -> action``."""

    def __init__(self, **params) -> None:
        _split(params)
        super().__init__(roco_fallback_align, dict(params), params)
