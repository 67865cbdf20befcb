"""Where the headroom above hand rule C lies, per kind of slot (privileged, not shipped).

    nice -n 10 python baselines/learned_select/headroom_c.py --out runs/headroom_c \
        [--noise 1.5 3.0] [--seeds 3] [--variants c untested_best ...] \
        [--choices roco_antialias roco_fallback roco coalign identity]

Hand rule C is ``reject_untested:tested=roco_fallback,tested_within_m=0.5`` (select mode
over [roco_antialias, roco_fallback]; a slot roco_antialias tested takes roco_fallback's
pose where it lies within 0.5 m of roco_antialias's, else roco_antialias's; an untested
slot is rejected). Each variant starts from C's action and changes decisions with the
true relative poses. Per slot, e = max(translation m, rotation deg) of each choice's pose
(the env's own alignments) against the truth. "The pair" is C's two choices; the env runs
``--choices`` (C's two first; more choices leave C's poses as they are):

* ``c``: C itself (its scores equal ``roco-env compare``'s for C on the same cells);
* ``untested_best``: an untested slot takes the pair's choice with the smallest e when it
  is <= ``--reject-error`` (default 1), else it is rejected as by C: the truth-best of
  {reject, roco_antialias, roco_fallback};
* ``untested_keep``: an untested slot takes the pair's choice with the smallest e, never
  rejected;
* ``tested_reject``: a tested slot is rejected where C's pose has e >
  ``--reject-error``;
* ``tested_far_best``: a tested slot where the pair's poses lie more than 0.5 m apart (C
  kept roco_antialias's) takes the pair's choice with the smallest e;
* ``tested_near_best``: a tested slot where they lie within 0.5 m (C took roco_fallback's)
  takes the pair's choice with the smallest e;
* ``both``: ``untested_best`` and ``tested_reject``;
* ``open_best``: ``untested_best`` and ``tested_far_best`` (every slot C's rule does
  not settle by the 0.5 m agreement);
* ``open_near_best``: ``open_best`` and ``tested_near_best``: every tested slot the pair's
  truth-closer pose, every untested one ``untested_best``'s;
* ``all_best``: every filled slot the choice of all ``--choices`` with the smallest e, or
  reject where every e > ``--reject-error``;
* ``ap_greedy_pair`` / ``ap_greedy``: AP-aware, slot by slot from C's action (one pass, in
  slot order), the option (the pair's choices or reject / every choice or reject) that
  maximises the agent's AP@0.7 on this frame with the other slots as they stand (ties keep
  the current one); the frame's AP is what the env's fusion and scoring would give
  (``env_hook.frame_evaluations``). A greedy bound on per-frame AP, not on the dataset AP
  the table reports;
* ``ap_greedy_open``: ``ap_greedy_pair`` on the slots a network behind C's guard could be
  given (untested, or tested with the pair within 0.5 m); a tested slot whose pair lies
  farther apart keeps roco_antialias's pose.

The episode plays C; every variant is scored on the same frames by fusing and scoring its
action as the env would (a select action changes neither the world nor the aligners'
state, only that step's fusion), and ``c`` so scored must equal the played episode's
AP@0.7 (else a RuntimeError). Cells of the README's grid (default: the held-out seeds 0-2
of the mixed benchmark, which is fine for a bound nobody ships). Writes ``results.jsonl``
in the ``roco-env compare`` layout (policy ``headroom_c_<variant>``) for ``table.py``, and
prints, per condition, the slots per kind from C's own episodes: filled, untested,
untested with a pair's choice within ``--reject-error`` (and of those, roco_fallback's),
tested with C's pose off by more; and with ``ap_greedy`` the slots it decides unlike C:
tested ones it rejects (and of those, how many C's pose put within ``--reject-error``),
tested ones it gives another choice, untested ones it keeps.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from env_hook import (
    choice_errors,
    frame_evaluations,
    print_counts,
    record_cell,
    run_with_env,
    select_decisions,
)
from privileged_bound import REJECT_ERROR, grid_parser

from roco_env.metrics import APAccumulator
from roco_env.policies.reject_untested import GAP_M, STATISTIC, tested_choice, untested_slots
from roco_env.policies.spec import parse_policy_spec
from roco_env.sweeps.cells import build_grid

RULE_C = "reject_untested:tested=roco_fallback,tested_within_m=0.5"
PAIR = ("roco_antialias", "roco_fallback")  # C's choices, first in --choices
VARIANTS = ("c", "untested_best", "untested_keep", "tested_reject", "tested_far_best",
            "tested_near_best", "both", "open_best", "open_near_best", "all_best",
            "ap_greedy_pair", "ap_greedy", "ap_greedy_open")
# variant -> (choices it tries, None: all; whether only the open slots: untested or near)
GREEDY = {"ap_greedy_pair": (len(PAIR), False), "ap_greedy": (None, False),
          "ap_greedy_open": (len(PAIR), True)}
WITHIN_M = parse_policy_spec(RULE_C).build().params.tested_within_m  # 0.5 m


def rule_c(untested: np.ndarray, choice_diagnostics: np.ndarray, reject: int) -> np.ndarray:
    """(n,) C's select actions: reject (index ``reject``) the ``untested`` (n,) slots, on
    the tested ones reject_untested's own :func:`tested_choice` over the (n, C, D)
    ``choice_diagnostics``: roco_fallback (1) where its ``gap_m`` is <= 0.5 m, else
    roco_antialias (0)."""
    return np.where(untested, reject,
                    tested_choice(choice_diagnostics, keep=0, prefer=1,
                                  within_m=WITHIN_M)).astype(np.int64)


def decide(variant: str, rule: np.ndarray, errors: np.ndarray, untested: np.ndarray,
           reject_error: float, gap: np.ndarray) -> np.ndarray:
    """(n,) select actions of ``variant``: C's ``rule`` (n,) changed with the (C, n) choice
    errors on the ``untested`` (n,) or tested slots (``gap`` (n,): m between the pair's
    poses); reject = the number of choices."""
    reject = len(errors)
    scope = errors if variant == "all_best" else errors[:len(PAIR)]
    best, best_error = np.argmin(scope, axis=0), scope.min(axis=0)
    best_or_reject = np.where(best_error <= reject_error, best, reject)
    if variant == "all_best":
        return best_or_reject.astype(np.int64)
    action = rule.copy()
    if variant in ("untested_best", "both", "open_best", "open_near_best"):
        action = np.where(untested, best_or_reject, action)
    tested_best = {"tested_far_best": gap > WITHIN_M, "open_best": gap > WITHIN_M,
                   "tested_near_best": gap <= WITHIN_M, "open_near_best": gap >= 0}
    if variant in tested_best:
        action = np.where(~untested & tested_best[variant], best, action)
    if variant == "untested_keep":
        action = np.where(untested, best, action)
    if variant in ("tested_reject", "both"):
        kept_error = np.take_along_axis(errors, np.minimum(rule, reject - 1)[None], 0)[0]
        action = np.where(~untested & (kept_error > reject_error), reject, action)
    return action.astype(np.int64)


def ap_greedy(rule: np.ndarray, options: list[int], slots: np.ndarray,
              frame_ap: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """(n,) select actions: from C's ``rule`` (n,), slot by slot over the indices
    ``slots`` in order, the value of ``options`` (select indices, the current one among
    them) whose action scores the highest ``frame_ap`` ((K, n) actions -> (K,) AP@0.7 of
    this frame, NaN counted lowest); a tie keeps the current value."""
    action = rule.copy()
    for slot in slots:
        trials = np.repeat(action[None], len(options), axis=0)
        trials[:, slot] = options
        scores = np.nan_to_num(frame_ap(trials), nan=-1.0)
        best = int(np.argmax(scores))
        if scores[best] > scores[options.index(action[slot])]:
            action = trials[best]
    return action


@dataclass(frozen=True)
class CFrame:
    """One evaluated agent's observation in C's episode, what a variant decides from: its n
    filled slots' (C, n) choice ``errors`` (m / deg, against the truth), (C, n, 3) choice
    ``poses`` T_{j->i} (x m, y m, yaw rad), (n,) ``gap`` (m between the pair's poses),
    (n,) ``untested`` and (n,) C's ``rule`` actions; ``evaluate`` scores (K, n) select
    actions on this frame (:func:`env_hook.frame_evaluations`)."""

    observation: dict
    errors: np.ndarray
    poses: np.ndarray
    gap: np.ndarray
    untested: np.ndarray
    rule: np.ndarray
    evaluate: Callable[[np.ndarray], list]

    def frame_ap(self, picks: np.ndarray) -> np.ndarray:
        """(K,) AP@0.7 of this frame with each row of the (K, n) select actions."""
        return np.array([evaluation.ap[0.7] for evaluation in self.evaluate(picks)])


def play_c(cell, choices: list[str], on_frame: Callable[[CFrame], None]) -> dict:
    """The env's metrics of ``cell`` played by C in an env whose ``action.choices`` are
    ``choices`` (the pair first), calling ``on_frame`` on every evaluated agent's
    observation before C acts on it."""
    if tuple(choices[:len(PAIR)]) != PAIR:
        raise ValueError(f"choices must start with {' '.join(PAIR)}; got {choices}")

    def make_act(index, env_of):
        def act(observation, info):
            env = env_of()
            alignments = env._choices[env.possible_agents[index]]
            mask = observation["collab_mask"]
            n, errors = choice_errors(alignments, observation, info)
            poses = np.stack([np.asarray(a.corrected, dtype=float)[:n]
                              for a in alignments])  # (C, n, 3)
            diagnostics = observation["choice_diagnostics"][:n]
            gap = diagnostics[:, 1, GAP_M]  # m between the pair's poses, as C reads it
            untested = untested_slots(observation["diagnostics"][:n, STATISTIC], mask[:n])
            rule = rule_c(untested, diagnostics, len(alignments))
            reported = info["privileged"]["reported_relative_poses"][:n]
            if info.get("evaluated", True):
                on_frame(CFrame(observation, errors, poses, gap, untested, rule,
                                lambda picks: frame_evaluations(
                                    env, index, select_decisions(reported, poses, picks))))
            action = np.full(len(mask), len(alignments), dtype=np.int64)
            action[:n] = rule
            return action
        act.env_overrides = {**parse_policy_spec(RULE_C).build().env_overrides,
                             "action.choices": list(choices)}
        return act
    return run_with_env(cell, "headroom_c_played", make_act)


def variant_picks(variant: str, frame: CFrame, reject_error: float) -> np.ndarray:
    """(n,) select actions of any variant on ``frame``: :func:`decide`'s, or
    :func:`ap_greedy`'s over the options and slots :data:`GREEDY` gives it."""
    if variant not in GREEDY:
        return decide(variant, frame.rule, frame.errors, frame.untested, reject_error,
                      frame.gap)
    tries, only_open = GREEDY[variant]
    reject = len(frame.errors)
    slots = (np.flatnonzero(frame.untested | (frame.gap <= WITHIN_M)) if only_open
             else np.arange(len(frame.rule)))
    return ap_greedy(frame.rule, [*range(tries or reject), reject], slots, frame.frame_ap)


def main(argv: list[str] | None = None) -> None:
    parser = grid_parser(__doc__.splitlines()[0], seeds=3)
    parser.set_defaults(noise=[1.5, 3.0])
    parser.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS))
    parser.add_argument("--reject-error", type=float, default=REJECT_ERROR,
                        help="m / deg: the pose error above which a slot is better rejected")
    parser.add_argument("--choices", nargs="+", default=list(PAIR),
                        help="the env's action.choices (policy specs), C's pair first")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    counts: dict = defaultdict(lambda: np.zeros(5, dtype=int))
    changes: dict = defaultdict(lambda: np.zeros(5, dtype=int))
    with (out / "results.jsonl").open("a") as sink:
        for cell in build_grid(args.scenarios, args.noise, [RULE_C],
                               list(range(args.seeds)), args.steps):
            scored = {variant: APAccumulator() for variant in args.variants}

            def on_frame(frame: CFrame, cell=cell, scored=scored) -> None:
                for variant, accumulator in scored.items():
                    picks = variant_picks(variant, frame, args.reject_error)
                    accumulator.add_stats(frame.evaluate(picks[None])[0].stats)
                    if variant == "ap_greedy":
                        _count_changes(changes, cell, frame, picks, args.reject_error)
                _count(counts, cell, frame, args.reject_error)
            played = play_c(cell, args.choices, on_frame)
            for variant, accumulator in scored.items():
                record_cell(sink, cell, f"headroom_c_{variant}",
                            {"ap70": accumulator.ap()[0.7]})
            if "c" in scored and not np.isclose(scored["c"].ap()[0.7], played["ap70"],
                                                rtol=0, atol=1e-9):
                raise RuntimeError(f"{cell}: C scored by the env {played['ap70']} and "
                                   f"by frame_evaluations {scored['c'].ap()[0.7]} differ")
    print_counts(f"filled slots | untested | untested, a choice within {args.reject_error:g} | "
                 f"of those, roco_fallback's best | tested, C's pose off > "
                 f"{args.reject_error:g}", counts)
    if changes:
        print_counts(f"ap_greedy's slots unlike C | tested, rejected | of those, C's pose within "
                     f"{args.reject_error:g} | tested, another choice | untested, kept", changes)


def _count_changes(changes: dict, cell, frame: CFrame, picks: np.ndarray,
                   reject_error: float) -> None:
    """Add to ``changes[(scenario, noise)]`` the slots where ``picks`` (n,) differ from C's
    action on ``frame``, by kind (the columns ``main`` prints)."""
    reject = len(frame.errors)
    changed, tested = picks != frame.rule, ~frame.untested
    rejected = changed & tested & (picks == reject)
    kept_error = np.take_along_axis(frame.errors, np.minimum(frame.rule, reject - 1)[None], 0)[0]
    changes[(cell.scenario, cell.noise)] += [
        int(changed.sum()), int(rejected.sum()), int(np.sum(rejected & (kept_error <= reject_error))),
        int(np.sum(changed & tested & (picks != reject))), int(np.sum(changed & frame.untested))]


def _count(counts: dict, cell, frame: CFrame, reject_error: float) -> None:
    """Add one observation's slots to ``counts[(scenario, noise)]`` (module docstring)."""
    errors, untested, action = frame.errors, frame.untested, frame.rule
    pair = errors[:len(PAIR)]
    best, rescued = np.argmin(pair, axis=0), pair.min(axis=0) <= reject_error
    kept = np.take_along_axis(errors, np.minimum(action, len(errors) - 1)[None], 0)[0]
    counts[(cell.scenario, cell.noise)] += [
        len(untested), int(np.sum(untested)), int(np.sum(untested & rescued)),
        int(np.sum(untested & rescued & (best == 1))),
        int(np.sum(~untested & (kept > reject_error)))]


if __name__ == "__main__":
    main()
