"""Runs from an installed wheel, outside the checkout: the scenario library and the learned
detector's weights ship, and step.

Called by ``make wheel-check`` with the fresh environment's python, from a folder
that holds no roco_env source, so every import below comes from the wheel.
"""

import sys
from pathlib import Path

import numpy as np

import roco_env

package = Path(roco_env.__file__).resolve().parent
if "site-packages" not in package.parts:
    sys.exit(f"roco_env was imported from {package}, not from the installed wheel")
names = roco_env.list_scenarios()
shipped = sorted(p.stem for p in (package / "scenarios").glob("*.yaml"))
if not names or names != shipped:
    sys.exit(f"list_scenarios() gives {names}; the wheel ships {shipped}")
for name in names:
    if name == "opv2v_replay":
        continue  # replays a dataset folder the user supplies (traffic.path)
    env = roco_env.parallel_env(name, max_cycles=3)
    observations, infos = env.reset(seed=0)
    steps = 0
    while env.agents:
        actions = {a: np.zeros(env.action_space(a).shape, dtype=np.float32) for a in env.agents}
        observations, rewards, terminations, truncations, infos = env.step(actions)
        steps += 1
    mean_ap = float(np.mean([rewards[a] for a in rewards]))
    print(f"wheel: {name}: {len(env.possible_agents)} agents, {steps} steps, "
          f"last mean AP@0.7 {mean_ap:.3f}")
from roco_env.sensing.learned import shipped_weights_path  # noqa: E402 (needs torch)

for fusion in ("gated", "max"):
    if not shipped_weights_path(fusion).is_file():
        sys.exit(f"the wheel lacks the shipped {fusion} weights {shipped_weights_path(fusion)}")
env = roco_env.parallel_env("urban_intersection", max_cycles=1, detector="learned",
                            fusion="intermediate")
env.reset(seed=0)
_, rewards, _, _, _ = env.step({a: np.zeros(env.action_space(a).shape, dtype=np.float32)
                                for a in env.agents})
print(f"wheel: learned detector, gated intermediate fusion: mean AP@0.7 "
      f"{float(np.mean(list(rewards.values()))):.3f}")
print(f"wheel check passed: {len(names)} scenarios shipped, imported from {package}")
