"""Time ``defend:base=roco`` per call, against another version of defend.py, on the same
recorded observations (one process, the machine's load shared by both).

    python baselines/attack_protocol/time_defend.py --against main

Records every agent's aligned observation and info of an urban_intersection episode
(noise 0.4, a 10 m spoof by cav_1, ``--steps`` steps), then replays them through a fresh
``Defend`` of this tree and one of ``git show REF:roco_env/policies/defend.py``,
interleaved ``--repeats`` times (``--old-tests``: this tree's without the mean-offset and
relative tests, added after 8bde3f5: compare with ``--against 8bde3f5``), and prints each one's median wall time per call (ms),
their ratio, and whether their actions agree on every call.
"""

from __future__ import annotations

import argparse
import functools
import importlib.util
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

import roco_env
from roco_env.policies import make_policy
from roco_env.policies.defend import Defend
from roco_env.policies.spec import merge_env_overrides

ATTACK = {"attack.kind": "pose_spoof", "attack.agents": ["cav_1"],
          "attack.params": {"offset_m": 10.0}}


def record(steps: int, seed: int = 0) -> list[tuple[dict, dict]]:
    """(observation, info) of every agent and step, in call order."""
    env = roco_env.parallel_env("urban_intersection", max_cycles=steps, sigma_t=0.4,
                                sigma_r=0.4, **merge_env_overrides(ATTACK, make_policy("defend")))
    policy = make_policy("defend")
    calls = []
    observations, infos = env.reset(seed=seed)
    while env.agents:
        calls += [(observations[a], infos[a]) for a in env.agents]
        actions = {a: policy(observations[a], infos[a]) for a in env.agents}
        observations, _, _, _, infos = env.step(actions)
    return calls


def load_defend(ref: str) -> type:
    """The ``Defend`` class of defend.py at git ``ref``."""
    source = subprocess.run(["git", "show", f"{ref}:roco_env/policies/defend.py"], check=True,
                            capture_output=True, text=True).stdout
    path = Path("/tmp") / f"defend_{ref.replace('/', '_')}.py"
    path.write_text(source, encoding="utf-8")
    spec = importlib.util.spec_from_file_location(f"defend_{ref}", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module.Defend


def replay(cls: type, calls: list[tuple[dict, dict]]) -> tuple[list[float], list[list[int]]]:
    """Wall time (s) and action of each call of a fresh ``cls()``."""
    policy, seconds, actions = cls(), [], []
    for observation, info in calls:
        start = time.perf_counter()
        action = policy(observation, info)
        seconds.append(time.perf_counter() - start)
        actions.append(action.tolist())
    return seconds, actions


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--against", default="main", help="git ref of the other defend.py")
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--old-tests", action="store_true",
                        help="this tree's Defend without the tests added after 8bde3f5 "
                        "(use_offset=False, use_relative=False): the same decisions")
    args = parser.parse_args()
    calls = record(args.steps)
    mine = functools.partial(Defend, use_offset=False, use_relative=False) if args.old_tests \
        else Defend
    versions = {"this tree": mine, args.against: load_defend(args.against)}
    times: dict[str, list[float]] = {name: [] for name in versions}
    actions: dict[str, list] = {}
    for _ in range(args.repeats):
        for name, cls in versions.items():
            seconds, actions[name] = replay(cls, calls)
            times[name] += seconds
    medians = {name: 1e3 * float(np.median(s)) for name, s in times.items()}
    for name, ms in medians.items():
        print(f"{name}: median {ms:.2f} ms per call ({len(times[name])} calls)")
    print(f"ratio {args.against} / this tree: {medians[args.against] / medians['this tree']:.2f}")
    same = actions["this tree"] == actions[args.against]
    print(f"actions identical on all {len(calls)} calls: {same}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
