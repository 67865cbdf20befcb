"""Per-frame alignment latency of roco and coalign (``python -m roco_env.perf alignment``).

Scenes from :func:`roco_env.policies.synthetic.benchmark_scene` (seeded) with
(agents, objects) = (2, 20), (5, 60), (10, 200); each line gives the median time
of one ``roco_align`` / ``coalign_align`` call. Baselines measured in the same
process: coalign, and roco with ``joint_every_round=True`` (the whole pose graph
solved in every matching round, the literal reading of the paper). The last line
reports how roco's cost grows with the object count (exponent of a power law
fitted through the three sizes).

Then the per-call time of every registered policy on the (5, 60) scene as an env
observation (4 collaborators), at the usual 0.8 m / 0.8 deg error and at 5 m / 5 deg,
where roco_fallback's prior-free fallback runs; ratios are to roco in the same process.
Budget of the prior-free aligners (ransac, v2i_calib, freealign): <= 10 ms per call.
"""

from __future__ import annotations

import numpy as np

from roco_env.perf._timing import median_seconds
from roco_env.policies import available_policies, make_policy
from roco_env.policies.coalign import coalign_align
from roco_env.policies.roco import roco_align
from roco_env.policies.synthetic import benchmark_scene, to_observation

SIZES = ((2, 20), (5, 60), (10, 200))
PRIOR_FREE = ("ransac", "v2i_calib", "freealign")
PRIOR_FREE_BUDGET_MS = 10.0


def run(quick: bool) -> list[str]:
    repeats = 5 if quick else 25
    lines, roco_ms = [], []
    for n_agents, n_objects in SIZES:
        scene = benchmark_scene(np.random.default_rng(0), n_agents, n_objects)
        args = scene.args()
        t_roco = median_seconds(lambda a=args: roco_align(*a), repeats, 2) * 1e3
        t_joint = (
            median_seconds(lambda a=args: roco_align(*a, joint_every_round=True), repeats, 1) * 1e3
        )
        t_coalign = median_seconds(lambda a=args: coalign_align(*a), repeats, 1) * 1e3
        roco_ms.append(t_roco)
        lines.append(
            f"agents={n_agents:2d} objects={n_objects:3d}: roco {t_roco:6.2f} ms | "
            f"roco joint-every-round {t_joint:6.2f} ms ({t_joint / t_roco:.2f}x slower) | "
            f"coalign {t_coalign:6.2f} ms (roco/coalign {t_roco / t_coalign:.2f}x)"
        )
    objects = np.array([s[1] for s in SIZES], dtype=float)
    slope = np.polyfit(np.log(objects), np.log(roco_ms), 1)[0]
    lines.append(
        f"roco cost growth: {roco_ms[0]:.2f} -> {roco_ms[1]:.2f} -> {roco_ms[2]:.2f} ms for "
        f"20 -> 60 -> 200 objects (agents grow too), ~objects^{slope:.2f}; "
        "target <= 3 ms at (5, 60)"
    )
    return lines + policy_lines(repeats)


def policy_lines(repeats: int) -> list[str]:
    """Median time of one call of every registered policy at (5, 60), two error sizes."""
    lines = []
    for error in (0.8, 5.0):
        scene = benchmark_scene(np.random.default_rng(0), 5, 60, error, error)
        obs = to_observation(scene, max_boxes=80, max_collaborators=4)
        info = {"privileged": {"true_relative_poses": scene.true,
                               "reported_relative_poses": scene.reported}}
        times = {}
        for name in available_policies():
            policy = make_policy(name)
            call = lambda p=policy, o=obs, i=info: p(o, i)  # noqa: E731
            times[name] = median_seconds(call, repeats, 1) * 1e3
        roco = times["roco"]
        parts = [f"{n} {t:.2f} ms ({t / roco:.2f}x)" for n, t in times.items()]
        lines.append(f"per call at (5, 60), error {error} m/{error} deg: " + " | ".join(parts))
        worst = max(PRIOR_FREE, key=times.get)
        lines.append(f"  slowest prior-free aligner: {worst} {times[worst]:.2f} ms "
                     f"(budget <= {PRIOR_FREE_BUDGET_MS:.0f} ms)")
    return lines
