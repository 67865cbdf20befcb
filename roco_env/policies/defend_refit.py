"""Alternative poses for a collaborator ``defend`` would reject for disagreeing: a re-fit
of its boxes alone (from its reported pose) against the boxes it should agree with, and its
reported pose (docs/attacks.md, "An honest collaborator left misaligned").

An honest collaborator whose pose the base aligner got wrong disagrees with everyone, like
a liar; under a pose that does not trust the failing fit its boxes agree again, while a
liar's forged, ghost or withheld boxes disagree under every pose. Metres and radians, the
ego frame unless said otherwise.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from roco_env.geometry import se2_apply, se2_inverse, transform_boxes
from roco_env.policies.prior_free import fit_se2

__all__ = ["alternative_poses", "refit_pose"]

MIN_PAIRS = 3  # a re-fit needs this many box pairs (fewer cannot fix a pose against noise)


def refit_pose(local: np.ndarray, start: np.ndarray, targets: np.ndarray,
               gates: tuple[float, ...]) -> np.ndarray | None:
    """The pose (3,) of a collaborator whose box centres ``local`` (k, 2, its own frame)
    best agree with ``targets`` (M, 2, ego frame): from ``start`` (3,), per gate in
    ``gates`` (m, widest first) each centre is paired with its nearest target within the
    gate and the pose re-fit to the pairs (least squares); None where a step has fewer than
    MIN_PAIRS pairs."""
    pose = np.asarray(start, dtype=float)
    if local.shape[0] < MIN_PAIRS or targets.shape[0] < MIN_PAIRS:
        return None
    tree = cKDTree(targets)
    for gate in gates:
        distance, nearest = tree.query(se2_apply(pose, local))
        near = distance < gate
        if int(near.sum()) < MIN_PAIRS:
            return None
        pose = fit_se2(local[near], targets[nearest[near]])
    return pose


def alternative_poses(boxes: np.ndarray, aligned: np.ndarray, reported: np.ndarray,
                      targets: np.ndarray, gates: tuple[float, ...]
                      ) -> list[tuple[np.ndarray, np.ndarray]]:
    """(pose (3,), boxes (k, 7) placed by it) for each alternative to the ``aligned`` pose
    (3,) that placed ``boxes`` (k, 7) in the ego frame: the :func:`refit_pose` from the
    ``reported`` pose (3,) against ``targets`` (M, 2) through ``gates`` (when it finds one),
    then the reported pose itself."""
    local = transform_boxes(boxes, se2_inverse(aligned))
    poses = [np.asarray(reported, dtype=float)]
    refit = refit_pose(local[:, :2], poses[0], targets, gates)
    if refit is not None:
        poses.insert(0, refit)
    return [(pose, transform_boxes(local, pose)) for pose in poses]
