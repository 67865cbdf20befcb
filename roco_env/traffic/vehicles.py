"""Vehicle classes and their size distributions.

Sizes are full lengths in metres (l, w, h). The class mix and the per-class
normal distributions (clipped to realistic bounds) follow typical urban fleet
statistics: mostly passenger cars, some vans, few trucks and buses.
Class indices refer to :data:`roco_env.traffic.state.OBJECT_CLASSES`.
"""

from __future__ import annotations

import numpy as np

from roco_env.traffic.state import OBJECT_CLASSES

# Share of each class in OBJECT_CLASSES order: car, van, truck, bus.
CLASS_MIX = np.array([0.78, 0.12, 0.06, 0.04])
# Per class: mean (l, w, h), std (l, w, h), min (l, w, h), max (l, w, h); metres.
_SIZE_MEAN = np.array([[4.5, 1.85, 1.50], [5.3, 2.00, 2.20], [9.5, 2.50, 3.40], [12.0, 2.55, 3.20]])
_SIZE_STD = np.array([[0.30, 0.08, 0.08], [0.30, 0.06, 0.15], [1.50, 0.05, 0.25], [0.50, 0.02, 0.10]])
_SIZE_MIN = np.array([[3.6, 1.60, 1.30], [4.7, 1.85, 1.90], [7.0, 2.30, 2.80], [10.5, 2.50, 3.00]])
_SIZE_MAX = np.array([[5.2, 2.05, 1.80], [6.0, 2.15, 2.70], [12.0, 2.60, 4.00], [13.5, 2.60, 3.50]])
# Desired-speed factor per class relative to the speed limit (heavy vehicles are slower).
SPEED_FACTOR = np.array([1.0, 0.95, 0.8, 0.8])

assert len(CLASS_MIX) == len(OBJECT_CLASSES)


def sample_classes(rng: np.random.Generator, n: int,
                   mix: np.ndarray = CLASS_MIX) -> np.ndarray:
    """Draw ``n`` class indices (int64) with probabilities ``mix``."""
    return rng.choice(len(OBJECT_CLASSES), size=n, p=mix / mix.sum()).astype(np.int64)


def sample_sizes(rng: np.random.Generator, classes: np.ndarray) -> np.ndarray:
    """Draw (l, w, h) in metres (N, 3) for the given class indices."""
    classes = np.asarray(classes, dtype=np.int64)
    noise = rng.standard_normal((classes.size, 3))
    sizes = _SIZE_MEAN[classes] + noise * _SIZE_STD[classes]
    return np.clip(sizes, _SIZE_MIN[classes], _SIZE_MAX[classes])
