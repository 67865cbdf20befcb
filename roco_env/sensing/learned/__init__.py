"""The learned BEV detector (torch): network, box targets/decoding, run-time model.

Imported only when ``detector="learned"`` is used (``import roco_env`` and the
parametric detectors never load it). See ``docs/perception.md``.
"""

from roco_env.sensing.learned.model import (
    LearnedDetector,
    load_checkpoint,
    make_learned_detector,
    save_checkpoint,
    sha256_of,
    shipped_weights_path,
)
from roco_env.sensing.learned.network import BevDetectorNet, NetConfig

__all__ = ["BevDetectorNet", "LearnedDetector", "NetConfig", "load_checkpoint",
           "make_learned_detector", "save_checkpoint", "sha256_of", "shipped_weights_path"]
