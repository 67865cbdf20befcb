"""Per-frame alignment latency of coalign, roco and roco_antialias
(``python -m roco_env.benchmarks alignment``).

Scenes from :func:`roco_env.testing.constructed_scenes.benchmark_scene` (seeded) with
(agents, objects) = (2, 20), (5, 60), (10, 200); each line gives the median time of one
``coalign_align`` / ``roco_align`` / ``antialias_align`` call on the same frame, the
calls interleaved round by round, timed as CPU time of this process (other processes'
load on a shared machine neither stretches nor favours any of them), and the ratios to
coalign. A second line per size times roco with
``joint_every_round=True`` (the whole pose graph solved in every matching round, the
literal reading of the paper). Then how roco's cost grows with the object count
(exponent of a power law fitted through the three sizes), and the env step rate on
``urban_intersection`` (4 CAVs + 1 RSU, every agent an ego with its own policy
instance, noise 0.8 m/deg) with each policy against the identity policy, whole seeded
episodes timed in turn.

Then the per-call time of every registered policy on the (5, 60) scene as an env
observation (4 collaborators), at the usual 0.8 m / 0.8 deg error and at 5 m / 5 deg,
where roco_fallback's prior-free fallback runs; ratios are to roco in the same process.
Budget of the prior-free aligners (ransac, v2i_calib, freealign): <= 10 ms per call.
"""

from __future__ import annotations

import functools
import statistics
import time
from collections.abc import Callable

import numpy as np

import roco_env
from roco_env.policies import available_policies, make_policy
from roco_env.policies.antialias import antialias_align
from roco_env.policies.coalign import coalign_align
from roco_env.policies.roco import roco_align
from roco_env.rollout import play_episode
from roco_env.testing.constructed_scenes import benchmark_scene, to_observation

SIZES = ((2, 20), (5, 60), (10, 200))
ENV_POLICIES = ("identity", "coalign", "roco", "roco_antialias")
PRIOR_FREE = ("ransac", "v2i_calib", "freealign")
PRIOR_FREE_BUDGET_MS = 10.0


def _episode(policy: str, steps: int) -> None:
    """One seeded urban_intersection episode of ``steps`` steps driven by ``policy``."""
    env = roco_env.parallel_env("urban_intersection", max_cycles=steps, sigma_t=0.8, sigma_r=0.8)
    for _ in play_episode(env, {agent: make_policy(policy) for agent in env.possible_agents},
                          seed=0):
        pass
    env.close()


def interleaved_medians(calls: dict[str, Callable[[], object]], repeats: int) -> dict[str, float]:
    """Median CPU seconds (``time.process_time``) of each call, timed in turn in every
    round after one warm-up round."""
    for fn in calls.values():
        fn()
    samples: dict[str, list[float]] = {name: [] for name in calls}
    for _ in range(repeats):
        for name, fn in calls.items():
            start = time.process_time()
            fn()
            samples[name].append(time.process_time() - start)
    return {name: statistics.median(values) for name, values in samples.items()}


def run(quick: bool) -> list[str]:
    repeats = 5 if quick else 25
    lines, roco_ms = [], []
    for n_agents, n_objects in SIZES:
        scene = benchmark_scene(np.random.default_rng(0), n_agents, n_objects)
        args = scene.args()
        ms = {
            name: 1e3 * seconds
            for name, seconds in interleaved_medians(
                {
                    "coalign": lambda a=args: coalign_align(*a),
                    "roco": lambda a=args: roco_align(*a),
                    "roco_antialias": lambda a=args: antialias_align(*a),
                },
                repeats,
            ).items()
        }
        t_joint = 1e3 * interleaved_medians(
            {"joint": lambda a=args: roco_align(*a, joint_every_round=True)}, repeats
        )["joint"]
        roco_ms.append(ms["roco"])
        lines.append(
            f"agents={n_agents:2d} objects={n_objects:3d}: coalign {ms['coalign']:6.2f} ms | "
            f"roco {ms['roco']:6.2f} ms ({ms['roco'] / ms['coalign']:.2f}x coalign) | "
            f"roco_antialias {ms['roco_antialias']:6.2f} ms "
            f"({ms['roco_antialias'] / ms['coalign']:.2f}x coalign)"
        )
        lines.append(
            f"    roco joint-every-round {t_joint:6.2f} ms ({t_joint / ms['roco']:.2f}x roco)"
        )
    objects = np.array([s[1] for s in SIZES], dtype=float)
    slope = np.polyfit(np.log(objects), np.log(roco_ms), 1)[0]
    lines.append(
        f"roco cost growth: {roco_ms[0]:.2f} -> {roco_ms[1]:.2f} -> {roco_ms[2]:.2f} ms for "
        "20 -> 60 -> 200 objects (agents grow too), "
        f"~objects^{slope:.2f}; target: roco and roco_antialias <= 1.5x coalign"
    )
    steps = 10 if quick else 30
    seconds = interleaved_medians(
        {name: lambda n=name: _episode(n, steps) for name in ENV_POLICIES}, 1 if quick else 3
    )
    rates = {name: steps / value for name, value in seconds.items()}
    lines.append(
        "env urban_intersection (5 agents, noise 0.8) steps/s: "
        + " | ".join(
            f"{name} {rate:.1f} ({rate / rates['identity']:.2f}x identity)"
            for name, rate in rates.items()
        )
        + "; target roco >= 0.4x identity"
    )
    return lines + policy_lines(repeats)


def policy_lines(repeats: int) -> list[str]:
    """Median CPU time of one call of every registered policy at (5, 60), two error sizes."""
    lines = []
    for error in (0.8, 5.0):
        scene = benchmark_scene(np.random.default_rng(0), 5, 60, error, error)
        obs = to_observation(scene, max_boxes=80, max_collaborators=4)
        # the ids every stateful policy keys its state by, as the env's info carries them
        info = {"agent": "ego",
                "collaborators": [f"collaborator_{j}"
                                  for j in range(int(obs["collab_mask"].sum()))],
                "privileged": {"true_relative_poses": scene.true,
                               "reported_relative_poses": scene.reported}}
        policies = {name: make_policy(name) for name in available_policies()}
        # a learned policy reads its own observation mode (env_overrides): not this scene's
        policies = {name: p for name, p in policies.items() if not hasattr(p, "env_overrides")}
        calls = {name: functools.partial(policy, obs, info) for name, policy in policies.items()}
        times = {name: 1e3 * s for name, s in interleaved_medians(calls, repeats).items()}
        roco = times["roco"]
        parts = [f"{n} {t:.2f} ms ({t / roco:.2f}x)" for n, t in times.items()]
        lines.append(f"per call at (5, 60), error {error} m/{error} deg: " + " | ".join(parts))
        worst = max(PRIOR_FREE, key=times.get)
        lines.append(f"  slowest prior-free aligner: {worst} {times[worst]:.2f} ms "
                     f"(budget <= {PRIOR_FREE_BUDGET_MS:.0f} ms)")
    return lines
