"""Where the headroom above hand rule C lies, per kind of slot (privileged, not shipped).

    nice -n 10 python baselines/learned_select/headroom_c.py --out runs/headroom_c \
        [--noise 1.5 3.0] [--seeds 3] [--variants c untested_best ...]

Hand rule C is ``reject_untested:tested=roco_fallback,tested_within_m=0.5`` (select mode
over [roco_antialias, roco_fallback]; a slot roco_antialias tested takes roco_fallback's
pose where it lies within 0.5 m of roco_antialias's, else roco_antialias's; an untested
slot is rejected). Each variant starts from C's action and changes one kind of decision
with the true relative poses. Per slot, e = max(translation m, rotation deg) of each
choice's pose (the env's own alignments) against the truth:

* ``c``: C itself (its scores equal ``roco-env compare``'s for C on the same cells);
* ``untested_best``: an untested slot takes the choice with the smallest e when it is
  <= ``--reject-error`` (default 1), else it is rejected as by C: the truth-best of
  {reject, roco_antialias, roco_fallback};
* ``untested_keep``: an untested slot takes the choice with the smallest e, never
  rejected;
* ``tested_reject``: a tested slot is rejected where C's pose has e >
  ``--reject-error``;
* ``tested_far_best``: a tested slot where the two choices' poses lie more than 0.5 m
  apart (C kept roco_antialias's) takes the choice with the smallest e;
* ``both``: ``untested_best`` and ``tested_reject``;
* ``open_best``: ``untested_best`` and ``tested_far_best`` (every slot C's rule does
  not settle by the 0.5 m agreement).

Cells of the README's grid (default: the held-out seeds 0-2 of the mixed benchmark, which
is fine for a bound nobody ships). Writes ``results.jsonl`` in the ``roco-env compare``
layout (policy ``headroom_c_<variant>``) for ``table.py``, and prints, per condition, the
slots per kind from C's own episodes: filled, untested, untested with a choice within
``--reject-error`` (and of those, roco_fallback's), tested with C's pose off by more.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
from env_hook import choice_errors, print_counts, record_cell, run_with_env
from privileged_bound import REJECT_ERROR, grid_parser

from roco_env.policies.reject_untested import GAP_M, STATISTIC, untested_slots
from roco_env.policies.spec import parse_policy_spec
from roco_env.sweeps.cells import build_grid

RULE_C = "reject_untested:tested=roco_fallback,tested_within_m=0.5"
VARIANTS = ("c", "untested_best", "untested_keep", "tested_reject", "tested_far_best", "both",
            "open_best")
WITHIN_M = 0.5  # C's tested_within_m


def decide(variant: str, rule: np.ndarray, errors: np.ndarray, untested: np.ndarray,
           reject_error: float, gap: np.ndarray) -> np.ndarray:
    """(n,) select actions of ``variant``: C's ``rule`` (n,) changed with the (C, n) choice
    errors on the ``untested`` (n,) or tested slots (``gap`` (n,): m between the two
    choices' poses); reject = the number of choices."""
    reject = len(errors)
    best, best_error = np.argmin(errors, axis=0), errors.min(axis=0)
    action = rule.copy()
    if variant in ("untested_best", "both", "open_best"):
        action = np.where(untested, np.where(best_error <= reject_error, best, reject), action)
    if variant in ("tested_far_best", "open_best"):
        action = np.where(~untested & (gap > WITHIN_M), best, action)
    if variant == "untested_keep":
        action = np.where(untested, best, action)
    if variant in ("tested_reject", "both"):
        kept_error = np.take_along_axis(errors, np.minimum(rule, reject - 1)[None], 0)[0]
        action = np.where(~untested & (kept_error > reject_error), reject, action)
    return action.astype(np.int64)


def main(argv: list[str] | None = None) -> None:
    parser = grid_parser(__doc__.splitlines()[0], seeds=3)
    parser.set_defaults(noise=[1.5, 3.0])
    parser.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS))
    parser.add_argument("--reject-error", type=float, default=REJECT_ERROR,
                        help="m / deg: the pose error above which a slot is better rejected")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    counts: dict = defaultdict(lambda: np.zeros(5, dtype=int))
    with (out / "results.jsonl").open("a") as sink:
        for variant in args.variants:
            for cell in build_grid(args.scenarios, args.noise, [RULE_C],
                                   list(range(args.seeds)), args.steps):
                def make_act(index, env_of, variant=variant, cell=cell):
                    rule_c = parse_policy_spec(RULE_C).build()

                    def act(observation, info):
                        env = env_of()
                        alignments = env._choices[env.possible_agents[index]]
                        mask = observation["collab_mask"]
                        n, errors = choice_errors(alignments, observation, info)
                        untested = untested_slots(
                            observation["diagnostics"][:n, STATISTIC], mask[:n])
                        action = rule_c(observation, info)
                        gap = observation["choice_diagnostics"][:n, 1, GAP_M]
                        action[:n] = decide(variant, action[:n], errors, untested,
                                            args.reject_error, gap)
                        if variant == "c":
                            _count(counts, cell, errors, untested, action[:n],
                                   args.reject_error)
                        return action
                    act.env_overrides = rule_c.env_overrides
                    return act
                label = f"headroom_c_{variant}"
                record_cell(sink, cell, label, run_with_env(cell, label, make_act))
    print_counts(f"filled slots | untested | untested, a choice within {args.reject_error:g} | "
                 f"of those, roco_fallback's best | tested, C's pose off > "
                 f"{args.reject_error:g}", counts)


def _count(counts: dict, cell, errors: np.ndarray, untested: np.ndarray, action: np.ndarray,
           reject_error: float) -> None:
    """Add one observation's slots to ``counts[(scenario, noise)]`` (module docstring)."""
    best, rescued = np.argmin(errors, axis=0), errors.min(axis=0) <= reject_error
    kept = np.take_along_axis(errors, np.minimum(action, len(errors) - 1)[None], 0)[0]
    counts[(cell.scenario, cell.noise)] += [
        len(untested), int(np.sum(untested)), int(np.sum(untested & rescued)),
        int(np.sum(untested & rescued & (best == 1))),
        int(np.sum(~untested & (kept > reject_error)))]


if __name__ == "__main__":
    main()
