"""Environment throughput: steps per second and the cost split by stage.

Setting: ``urban_intersection`` with 4 CAVs + 1 RSU (5 agents, every
one evaluated as an ego), the lowest density (step 0.5) giving at least 100
vehicles at reset, identity policy, late fusion. The per-step cost varies along
an episode (signal phases, queues), so whole episodes from a seeded reset are
timed. Baselines measured in the same process, on the first frame: the
late-fusion NMS of all egos done one ego at a time with ``geometry.nms_bev``
(the plain implementation) against the batched NMS the env uses (identical
kept boxes), and the AP matching of all egos one ego at a time with
``metrics.frame_stats`` against the batched ``metrics.match_frames`` the env
uses (identical tp flags).
"""

from __future__ import annotations

import cProfile
import io
import pstats
import time

import numpy as np

from roco_env.action_modes import Decision
from roco_env.batched_nms import batched_nms_bev
from roco_env.benchmarks._timing import median_seconds
from roco_env.env import CollabPerceptionEnv
from roco_env.evaluation import ground_truths
from roco_env.fusion import merge_into_ego_frame
from roco_env.geometry import nms_bev
from roco_env.metrics import frame_stats, match_frames
from roco_env.policies.basic import IdentityPolicy
from roco_env.rollout import play_episode

SETTING = dict(scenario="urban_intersection", cavs=4, rsus=1, fusion="late")
TARGET_VEHICLES = 100
TARGET_STEPS_PER_S = 200.0


def _env() -> CollabPerceptionEnv:
    """The benchmark env, reset with seed 0, at the density giving TARGET_VEHICLES."""
    for density in np.arange(2.0, 20.0, 0.5):
        env = CollabPerceptionEnv(**SETTING, density=float(density), max_cycles=10**9)
        env.reset(seed=0)
        if env.unwrapped._frame.state.num_objects >= TARGET_VEHICLES:
            return env
    raise ValueError(f"no density up to 20 gives {TARGET_VEHICLES} vehicles")


def _episode(env: CollabPerceptionEnv, steps: int) -> None:
    """Steps 1..``steps`` after a seeded reset (the cost varies along an episode), every
    agent with the identity policy."""
    policies = dict.fromkeys(env.possible_agents, IdentityPolicy())
    for _ in play_episode(env, policies, seed=0, max_steps=steps):
        pass


def run(quick: bool) -> list[str]:
    steps, repeats = (100, 3) if quick else (500, 3)
    env = _env()
    frame = env.unwrapped._frame
    lines = [f"setting: {env.config.name}, {len(env.possible_agents)} agents (all evaluated), "
             f"{frame.state.num_objects} vehicles (density {env.config.traffic.density}), "
             "identity policy, late fusion"]

    def episode() -> None:
        _episode(env, steps)

    seconds = median_seconds(episode, repeats=repeats, warmup=1)
    rate = steps / seconds
    lines.append(f"env.step over {steps}-step episodes: {1e3 * seconds / steps:.2f} ms/step "
                 f"(median of {repeats}) -> {rate:.0f} steps/s (target "
                 f"{TARGET_STEPS_PER_S:.0f}: {'met' if rate >= TARGET_STEPS_PER_S else 'NOT met'})")

    env.clock.enabled = True
    start = time.perf_counter()
    episode()
    wall = time.perf_counter() - start
    env.clock.enabled = False
    split = dict(env.clock.seconds)
    split["other (env glue, policy)"] = wall - sum(split.values())
    lines.append(f"cost split by stage (one more episode, {1e3 * wall / steps:.2f} ms/step):")
    for stage, spent in sorted(split.items(), key=lambda item: -item[1]):
        lines.append(f"  {stage:<26} {1e3 * spent / steps:6.2f} ms/step "
                     f"({100 * spent / wall:4.1f}%)")

    merged = [merge_into_ego_frame(v.boxes, v.scores, v.collab_boxes, v.collab_scores,
                                   v.reported_relative) for v in frame.views]
    thr = env.config.fusion.nms_iou
    boxes, scores = [m.boxes for m in merged], [m.scores for m in merged]
    plain = median_seconds(lambda: [nms_bev(b, s, thr) for b, s in zip(boxes, scores,
                                                                         strict=True)],
                           repeats=repeats * 3)
    batched = median_seconds(lambda: batched_nms_bev(boxes, scores, thr), repeats=repeats * 3)
    same = all(np.array_equal(a, b) for a, b in zip(
        batched_nms_bev(boxes, scores, thr), [nms_bev(b, s, thr) for b, s in
                                              zip(boxes, scores, strict=True)], strict=True))
    lines.append(f"late-fusion NMS of {len(merged)} egos on the first frame "
                 f"({sum(len(b) for b in boxes)} boxes): "
                 f"batched {1e3 * batched:.2f} ms vs per-ego nms_bev {1e3 * plain:.2f} ms -> "
                 f"{plain / batched:.1f}x, identical kept boxes: {same}")
    lines.append(_matching_line(env, repeats * 3))
    if not quick:
        lines += _profile(env, steps)
    return lines


def _matching_line(env: CollabPerceptionEnv, repeats: int) -> str:
    """Per-ego ``frame_stats`` vs batched ``match_frames`` on the first frame's fused boxes."""
    frame = env.unwrapped._frame
    keep_all = {a: Decision(v.reported_relative, np.ones(len(v.collaborators), dtype=bool))
                for a, v in zip(env.possible_agents, frame.views, strict=True)}
    fused, _ = env._fuse(frame, keep_all)
    evaluation = env.config.evaluation
    gts = ground_truths(frame.state, frame.visibility.visible,
                        [(v.agent, v.collaborators) for v in frame.views],
                        evaluation.x_range, evaluation.y_range)
    frames = [(f.boxes, f.scores, gt) for f, (gt, _) in zip(fused.values(), gts, strict=True)]
    per_ego = median_seconds(lambda: [frame_stats(*f) for f in frames], repeats=repeats)
    batched = median_seconds(lambda: match_frames(frames), repeats=repeats)
    same = all(np.array_equal(a.tp, b.tp) for a, b in zip(
        match_frames(frames), [frame_stats(*f) for f in frames], strict=True))
    return (f"AP matching of {len(frames)} egos on the first frame "
            f"({sum(len(f[1]) for f in frames)} predictions, "
            f"{sum(len(f[2]) for f in frames)} GT): batched {1e3 * batched:.2f} ms vs per-ego "
            f"frame_stats {1e3 * per_ego:.2f} ms -> {per_ego / batched:.1f}x, "
            f"identical tp: {same}")


def _profile(env: CollabPerceptionEnv, steps: int, top: int = 6) -> list[str]:
    profiler = cProfile.Profile()
    profiler.enable()
    _episode(env, steps)
    profiler.disable()
    out = io.StringIO()
    pstats.Stats(profiler, stream=out).sort_stats("tottime").print_stats(top)
    rows = [line for line in out.getvalue().splitlines() if "/" in line or "{" in line]
    return ["cProfile, top functions by own time (ncalls tottime percall cumtime percall):"] + [
        "  " + " ".join(row.split()) for row in rows[:top]]
