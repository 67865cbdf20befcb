"""How often roco_antialias makes a pose worse than reported on periodic lattices
(``python -m roco_env.benchmarks lattice_harm``).

Scenes from :func:`roco_env.testing.constructed_scenes.lattice_scene` (seeded): identical
cars in rows with a pitch drawn uniformly from [2.4, 8] m, the collaborator's reported pose
off by Gaussian errors of std s m (x, y) and s deg at each level s. Per level and pooled, for
roco_antialias, roco_antialias without its ambiguity diagnosis (``use_ambiguity=False``,
the aligner before it) and roco, on the same scenes: the share of poses made more than
0.5 m worse than reported (translation error after > before + 0.5 m, the stress search's
``harm``) and Success@1m1deg after the correction.
"""

from __future__ import annotations

import numpy as np

from roco_env.geometry import wrap_angle
from roco_env.policies.antialias import antialias_align
from roco_env.policies.roco import roco_align
from roco_env.testing.constructed_scenes import lattice_scene

LEVELS = (0.5, 1.0, 2.0, 3.0)  # m and deg
PITCH = (2.4, 8.0)  # m
HARM_MARGIN = 0.5  # m, as roco_env.stress.objectives.HARM_MARGIN
ALIGNERS = {
    "roco_antialias": lambda scene: antialias_align(*scene.args())[0],
    "roco_antialias:use_ambiguity=false":
        lambda scene: antialias_align(*scene.args(), use_ambiguity=False)[0],
    "roco": lambda scene: roco_align(*scene.args()),
}


def _outcomes(scene, corrected: np.ndarray) -> tuple[bool, bool]:
    """(made worse than reported, within 1 m and 1 deg) of the one collaborator's pose."""
    before = np.hypot(*(scene.reported[0, :2] - scene.true[0, :2]))
    after = np.hypot(*(corrected[0, :2] - scene.true[0, :2]))
    yaw = abs(wrap_angle(corrected[0, 2] - scene.true[0, 2]))
    return bool(after > before + HARM_MARGIN), bool(after <= 1.0 and yaw <= np.deg2rad(1.0))


def run(quick: bool = False) -> list[str]:
    """One line per noise level and one pooled: harm % and Success@1m1deg % per aligner."""
    scenes = 20 if quick else 500
    lines, pooled = [], {name: [] for name in ALIGNERS}
    for level in LEVELS:
        rng = np.random.default_rng(int(level * 10))
        batch = [lattice_scene(rng, rng.uniform(*PITCH), level, level) for _ in range(scenes)]
        cells = []
        for name, align in ALIGNERS.items():
            outcomes = [_outcomes(scene, align(scene).corrected) for scene in batch]
            pooled[name] += outcomes
            harm, success = np.mean(outcomes, axis=0) * 100
            cells.append(f"{name} {harm:4.1f}% / {success:5.1f}%")
        lines.append(f"noise {level:.1f} m/deg, {scenes} lattices (harm / Success@1m1deg): "
                     + ", ".join(cells))
    totals = [f"{name} {np.mean(o, axis=0)[0] * 100:4.2f}% / {np.mean(o, axis=0)[1] * 100:5.1f}%"
              for name, o in pooled.items()]
    lines.append(f"all {len(LEVELS) * scenes} lattices, pitch {PITCH[0]}-{PITCH[1]} m: "
                 + ", ".join(totals) + "; target: roco_antialias harm <= 1%")
    return lines
