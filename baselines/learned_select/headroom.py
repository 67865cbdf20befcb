"""Where the headroom above ``reject_untested`` lies, per kind of decision (training seeds).

    nice -n 10 python baselines/learned_select/headroom.py --out runs/headroom \
        [--noise 0.2 3.0] [--seeds 4] [--variants rule untested_best tested_best ...]

Each variant is a privileged select-mode policy (identity / coalign / roco /
roco_antialias, aligned observation, not shipped) that starts from the rule
``reject_untested`` (roco_antialias's pose; reject the slots roco_antialias computed no
statistic for) and changes one kind of decision with the true relative poses. Per slot,
e = max(translation m, rotation deg) of each choice's pose (the env's own alignments)
against the truth:

* ``rule``: the rule itself;
* ``untested_best``: an untested slot takes the choice with the smallest e when it is
  <= 1 (else it is rejected, as by the rule);
* ``tested_best``: a tested slot takes the choice with the smallest e (never rejected);
* ``tested_reject``: a tested slot is rejected when roco_antialias's e >
  ``--reject-error`` (default 1);
* ``bound``: all three changes.

Env seeds 1,000,000 and up (the training range; never the held-out 0-2). Writes
``results.jsonl`` in the ``roco-env compare`` layout (policy ``headroom_<variant>``) for
``table.py``, and prints, per condition and kind of slot, how many slots each change
touches (from the rule's episodes).
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
from env_hook import choice_errors, print_counts, record_cell, run_with_env
from privileged_bound import CHOICES, REJECT_ERROR, grid_parser

from roco_env.policies import make_policy
from roco_env.policies.reject_untested import STATISTIC, untested_slots
from roco_env.sweeps.cells import build_grid
from roco_env.training.rl.curriculum import TRAIN_SEED_BASE

KEEP, REJECT = CHOICES.index("roco_antialias"), len(CHOICES)
VARIANTS = ("rule", "untested_best", "tested_best", "tested_reject", "bound")
FINER_M = 0.1  # a choice "is finer" when its e is below roco_antialias's by this much


def decide(variant: str, errors: np.ndarray, tested: np.ndarray,
           reject_error: float = REJECT_ERROR) -> np.ndarray:
    """(n,) select actions of ``variant`` from the (C, n) choice errors and (n,) tested;
    ``reject_error``: tested_reject's threshold on roco_antialias's e."""
    best, best_error = np.argmin(errors, axis=0), errors.min(axis=0)
    best_or_reject = np.where(best_error <= REJECT_ERROR, best, REJECT)
    untested = best_or_reject if variant in ("untested_best", "bound") else REJECT
    kept = np.full(len(tested), KEEP)
    if variant in ("tested_best", "bound"):
        kept = best if variant == "tested_best" else best_or_reject
    elif variant == "tested_reject":
        kept = np.where(errors[KEEP] > reject_error, REJECT, KEEP)
    return np.where(tested, kept, untested).astype(np.int64)


def main(argv: list[str] | None = None) -> None:
    parser = grid_parser(__doc__.splitlines()[0], seeds=4)
    parser.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS))
    parser.add_argument("--reject-error", type=float, default=REJECT_ERROR,
                        help="tested_reject: reject where roco_antialias's e exceeds this")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    overrides = dict(make_policy("learned_select").env_overrides)
    seeds = [TRAIN_SEED_BASE + index for index in range(args.seeds)]
    counts: dict = defaultdict(lambda: np.zeros(5, dtype=int))
    with (out / "results.jsonl").open("a") as sink:
        for variant in args.variants:
            for cell in build_grid(args.scenarios, args.noise, ["roco_antialias"], seeds,
                                   args.steps):
                def make_act(index, env_of, variant=variant, cell=cell):
                    def act(observation, info):
                        env = env_of()
                        alignments = env._choices[env.possible_agents[index]]
                        n, errors = choice_errors(alignments, observation, info)
                        tested = ~untested_slots(
                            observation["choice_diagnostics"][:n, KEEP, STATISTIC],
                            observation["collab_mask"][:n])
                        action = np.full(len(observation["collab_mask"]), KEEP)
                        action[:n] = decide(variant, errors, tested, args.reject_error)
                        if variant == "rule":
                            _count(counts, cell, errors, tested)
                        return action
                    act.env_overrides = overrides
                    return act
                label = f"headroom_{variant}" + (
                    f"_{args.reject_error:g}" if variant == "tested_reject" else "")
                record_cell(sink, cell, label, run_with_env(cell, label, make_act))
    print_counts("slots | tested: finer choice | tested: off > 1 | untested | "
                 "untested: a choice within 1", counts)


def _count(counts: dict, cell, errors: np.ndarray, tested: np.ndarray) -> None:
    """Add one observation's slots to ``counts[(scenario, noise)]``: filled slots, tested slots where a
    choice is finer than roco_antialias by FINER_M, tested slots off by more than 1,
    untested slots, and untested ones some choice puts within 1."""
    finer = errors.min(axis=0) < errors[KEEP] - FINER_M
    off = errors[KEEP] > REJECT_ERROR
    rescued = errors.min(axis=0) <= REJECT_ERROR
    counts[(cell.scenario, cell.noise)] += [len(tested), int(np.sum(tested & finer)),
                                            int(np.sum(tested & off)), int(np.sum(~tested)),
                                            int(np.sum(~tested & rescued))]


if __name__ == "__main__":
    main()
