"""Fusion of an ego's own outputs with its collaborators' (docs/architecture.md, step 3).

``late_fusion`` merges boxes (the default; ``merge_many`` and ``suppress``
merge and NMS many egos at once); ``roco_env.fusion.intermediate``
warps, gates and max-fuses BEV feature maps (imported on demand: it needs torch).
"""

from roco_env.fusion.late import (
    EGO_SOURCE,
    FusedDetections,
    late_fusion,
    merge_into_ego_frame,
    merge_many,
    suppress,
)

__all__ = ["EGO_SOURCE", "FusedDetections", "late_fusion", "merge_into_ego_frame", "merge_many",
           "suppress"]
