"""How often roco_antialias makes a pose worse than reported on periodic lattices
(``python -m roco_env.benchmarks lattice_harm``).

Scenes from :func:`roco_env.testing.constructed_scenes.lattice_scene` (seeded): identical
cars in rows with a pitch drawn uniformly from [2.4, 8] m, the collaborator's reported pose
off by Gaussian errors of std s m (x, y) and s deg at each level s. Per level and pooled, for
the reported pose itself (identity: the reference, never worse by definition),
roco_antialias, roco_antialias without its ambiguity diagnosis (``use_ambiguity=False``,
the aligner before it) and roco, on the same scenes: the share of poses made more than
:data:`~roco_env.metrics.HARM_MARGIN` = 0.5 m worse than reported
(:func:`~roco_env.metrics.harm_share`, the stress search's ``harm``) and Success@1m1deg
(:func:`~roco_env.metrics.success_rate`) after the correction.
"""

from __future__ import annotations

import numpy as np

from roco_env.metrics import harm_share, relative_pose_error, success_rate
from roco_env.policies.antialias import antialias_align
from roco_env.policies.roco import roco_align
from roco_env.testing.constructed_scenes import lattice_scene

LEVELS = (0.5, 1.0, 2.0, 3.0)  # m and deg
PITCH = (2.4, 8.0)  # m
ALIGNERS = {
    "reported pose (identity)": lambda scene: scene.reported,
    "roco_antialias": lambda scene: antialias_align(*scene.args())[0].corrected,
    "roco_antialias:use_ambiguity=false":
        lambda scene: antialias_align(*scene.args(), use_ambiguity=False)[0].corrected,
    "roco": lambda scene: roco_align(*scene.args()).corrected,
}


def _errors(scenes: list, align) -> tuple[np.ndarray, np.ndarray]:
    """The errors (N, 2) (m, deg) of the one collaborator's pose of each scene, as reported
    and after ``align`` (scene -> corrected poses (1, 3))."""
    before = np.concatenate([relative_pose_error(s.reported, s.true) for s in scenes])
    after = np.concatenate([relative_pose_error(align(s), s.true) for s in scenes])
    return before, after


def _cell(name: str, before: np.ndarray, after: np.ndarray, digits: int) -> str:
    harm, success = harm_share(before, after) * 100, success_rate(after, 1.0) * 100
    return f"{name} {harm:4.{digits}f}% / {success:5.1f}%"


def run(quick: bool = False) -> list[str]:
    """One line per noise level and one pooled: harm % and Success@1m1deg % per aligner."""
    scenes = 20 if quick else 500
    lines, pooled = [], {name: ([], []) for name in ALIGNERS}
    for level in LEVELS:
        rng = np.random.default_rng(int(level * 10))
        batch = [lattice_scene(rng, rng.uniform(*PITCH), level, level) for _ in range(scenes)]
        cells = []
        for name, align in ALIGNERS.items():
            before, after = _errors(batch, align)
            pooled[name][0].append(before)
            pooled[name][1].append(after)
            cells.append(_cell(name, before, after, 1))
        lines.append(f"noise {level:.1f} m/deg, {scenes} lattices (harm / Success@1m1deg): "
                     + ", ".join(cells))
    totals = [_cell(name, np.concatenate(b), np.concatenate(a), 2)
              for name, (b, a) in pooled.items()]
    lines.append(f"all {len(LEVELS) * scenes} lattices, pitch {PITCH[0]}-{PITCH[1]} m: "
                 + ", ".join(totals) + "; target: roco_antialias harm <= 1%")
    return lines
