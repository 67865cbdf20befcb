"""Intermediate-fusion plumbing: warp collaborators' BEV maps into the ego grid and max-fuse.

Each collaborator's map (C, H, W), in its own true sensor frame on the shared
:class:`~roco_env.sensing.BevGrid`, is resampled into the ego frame with the
*corrected* relative pose T_{j->i} (bilinear, zero padding, via
:func:`roco_env.sensing.warp_bev`), then fused with the ego's map by an
element-wise maximum. Decoding fused maps into boxes is
not part of this module (a later issue).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from roco_env.sensing import BevGrid, warp_bev


def fuse_features(ego_features: torch.Tensor, collab_features: Sequence[torch.Tensor],
                  relative_poses: np.ndarray, grid: BevGrid) -> torch.Tensor:
    """Max-fused map (C, H, W) in the ego frame.

    relative_poses (N, 3): corrected T_{j->i} per collaborator (x m, y m, yaw rad),
    one per entry of ``collab_features``.
    """
    relative_poses = np.asarray(relative_poses, dtype=float).reshape(-1, 3)
    if relative_poses.shape[0] != len(collab_features):
        raise ValueError(
            "relative_poses must hold one pose per collaborator map; got "
            f"{relative_poses.shape[0]} poses for {len(collab_features)} maps"
        )
    if not collab_features:
        return ego_features.clone()
    warped = warp_bev(torch.stack(list(collab_features)), relative_poses, grid)
    return torch.maximum(ego_features, warped.amax(dim=0))
