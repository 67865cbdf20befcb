"""Where roco_antialias's pose goes wrong, by what its choice diagnostics say (training seeds).

    nice -n 10 python baselines/learned_select/slot_errors.py --noise 0.2 0.8 1.5 3.0 --seeds 10

Plays ``learned_select`` (``--policy``, any select-mode policy spec reading
``choice_diagnostics``, e.g. ``learned_select:weights=W``) on the mixed benchmark's scenarios at training env seeds (1,000,000 and up), and for every
filled slot of every agent's observation compares roco_antialias's pose (the env's own
select-mode alignment) with the privileged true relative pose: error = max(translation m,
rotation deg). Prints per condition and kind of slot (roco_antialias ``tested`` it: a
significance statistic, or not; ``moved`` it: applied a correction, or not) the slots, how
many are off by more than 1 (m / deg), the median error, how many the policy rejected and
how many it gave another choice than roco_antialias ("switched").
"""

from __future__ import annotations

import argparse
from collections import defaultdict

import numpy as np
from env_hook import run_with_env
from privileged_bound import CHOICES, pose_errors

from roco_env.policies.reject_untested import NO_STATISTIC, STATISTIC
from roco_env.policies.spec import parse_policy_spec
from roco_env.sweeps.cells import build_grid
from roco_env.training.rl.curriculum import TRAIN_SEED_BASE

KEEP = CHOICES.index("roco_antialias")
APPLIED = 0  # column of roco_env.observation_modes.CHOICE_DIAGNOSTICS (STATISTIC too)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", default="learned_select")
    parser.add_argument("--scenarios", nargs="+",
                        default=["urban_intersection", "parking_lot", "v2xset_like"])
    parser.add_argument("--noise", nargs="+", type=float, default=[0.2, 0.8, 1.5, 3.0])
    parser.add_argument("--seeds", type=int, default=10)
    args = parser.parse_args(argv)
    rows: dict = defaultdict(list)  # (scenario, noise, kind) -> [(error, rejected, switched)]
    seeds = [TRAIN_SEED_BASE + index for index in range(args.seeds)]
    for cell in build_grid(args.scenarios, args.noise, ["roco_antialias"], seeds, 10):

        def recorder(index, env_of, cell=cell):
            policy = parse_policy_spec(args.policy).build()

            def act(observation, info):
                action = policy(observation, info)
                env = env_of()
                alignment = env._choices[env.possible_agents[index]][KEEP]
                n = int(np.sum(observation["collab_mask"]))
                errors = pose_errors(np.asarray(alignment.corrected)[:n],
                                     info["privileged"]["true_relative_poses"][:n])
                for slot in range(n):
                    own = observation["choice_diagnostics"][slot, KEEP]
                    kind = ("tested" if own[STATISTIC] != NO_STATISTIC else "untested") + \
                        (", moved" if own[APPLIED] else ", not moved")
                    rows[(cell.scenario, cell.noise, kind)].append(
                        (errors[slot], action[slot] == len(CHOICES),
                         action[slot] not in (KEEP, len(CHOICES))))
                return action
            act.env_overrides = policy.env_overrides
            return act
        run_with_env(cell, args.policy, recorder)
    print("| scenario | noise | roco_antialias's slot | slots | off > 1 | median error | "
          "rejected | switched |\n|---|---|---|---|---|---|---|---|")
    for (scenario, noise, kind), values in sorted(rows.items()):
        errors = np.array([value[0] for value in values])
        print(f"| {scenario} | {noise} | {kind} | {len(values)} | {int(np.sum(errors > 1))} | "
              f"{np.median(errors):.2f} | {sum(value[1] for value in values)} | "
              f"{sum(value[2] for value in values)} |")


if __name__ == "__main__":
    main()
