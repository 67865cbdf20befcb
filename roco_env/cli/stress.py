"""``roco-env stress``: search for the scenarios where an alignment policy breaks.

One Optuna study per policy (SQLite, OUT/study.db) maximises the objective over the
search space (--space, default roco_env/stress/default_space.yaml): each evaluation
builds a scenario from the sampled parameters and runs the policy for each of --seeds
for --steps steps. Objectives (larger = worse for the policy): harm (share of
collaborator poses made > 0.5 m worse than reported), success (minus Success@1m1deg),
ap70 (minus AP@0.7), gap (oracle AP@0.7 minus the policy's). --budget counts completed
evaluations; the same command resumes an interrupted search. Writes per policy the 3
worst scenarios (YAML), a plot of the objective over trials and a GIF of the worst
episode, OUT/report.md, and prints one summary line per policy. See docs/stress.md.
"""

from __future__ import annotations

import argparse

from roco_env.cli.render import render_episode
from roco_env.stress.objectives import OBJECTIVES
from roco_env.stress.report import evaluate_reference, export_worst, section, write_report
from roco_env.stress.space import load_space
from roco_env.stress.study import BACKENDS, SAMPLERS, SearchSettings, check_settings, run_search
from roco_env.sweeps.grid import Cell
from roco_env.sweeps.spec import parse_policy_spec


def run(args: argparse.Namespace) -> int:
    if args.address is not None and args.backend != "ray":
        raise ValueError("--address needs --backend ray")
    if args.workers < 1:
        raise ValueError(f"--workers: workers must be an integer >= 1; got {args.workers}")
    space = load_space(args.space)
    all_settings = [
        SearchSettings(out=args.out, policy=parse_policy_spec(policy).label,
                       objective=args.objective, budget=args.budget, seeds=tuple(args.seeds),
                       steps=args.steps, space=space, sampler=args.sampler, seed=args.seed)
        for policy in dict.fromkeys(args.policy)]
    for settings in all_settings:  # every bad setting is refused before any search starts
        check_settings(settings)
    sections, summaries = [], []
    for settings in all_settings:
        study = run_search(settings, backend=args.backend, workers=args.workers,
                           address=args.address)
        found = export_worst(settings, study)
        gif = None
        if found and not args.no_gif:
            gif = settings.folder / "worst_episode.gif"
            render_episode(Cell(str(found[0].path), None, settings.policy, settings.seeds[0],
                                settings.steps), gif=gif)
        text, summary = section(settings, study, found, evaluate_reference(settings),
                                None if gif is None else str(gif))
        sections.append(text)
        summaries.append(summary)
    report = write_report(args.out, sections, summaries)
    for summary in summaries:
        print(summary)
    print(f"report: {report}")
    return 0


def _seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expects an integer >= 0; got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"expects an integer >= 0; got {value}")
    return value


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("stress", help="search for the scenarios where a policy "
                                   "breaks (Optuna)", description=__doc__,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", nargs="+", required=True, metavar="SPEC",
                        help="policy spec(s), one search each, e.g. roco roco_antialias coalign")
    parser.add_argument("--objective", choices=OBJECTIVES, default="harm",
                        help="what the search makes worst (default: harm)")
    parser.add_argument("--budget", type=int, default=100,
                        help="completed evaluations per policy (default: 100)")
    parser.add_argument("--space", default=None, metavar="FILE",
                        help="YAML of parameter ranges (default: the shipped default space)")
    parser.add_argument("--seeds", type=_seed, nargs="+", default=[0],
                        help="episode seeds of every evaluation (default: 0)")
    parser.add_argument("--steps", type=int, default=5,
                        help="env steps per episode (default: 5)")
    parser.add_argument("--out", required=True, metavar="DIR",
                        help="output folder (study.db, scenarios, report.md); re-running resumes")
    parser.add_argument("--backend", choices=BACKENDS, default="local",
                        help="local processes or Ray tasks (default: local)")
    parser.add_argument("--workers", type=int, default=1,
                        help="parallel workers sharing the study (default: 1)")
    parser.add_argument("--address", default=None,
                        help="Ray cluster address for --backend ray (default: a local Ray)")
    parser.add_argument("--sampler", choices=SAMPLERS, default="tpe",
                        help="Optuna sampler (default: tpe)")
    parser.add_argument("--seed", type=_seed, default=0, help="sampler seed (default: 0)")
    parser.add_argument("--no-gif", action="store_true",
                        help="skip the GIF of the worst episode")
    parser.set_defaults(func=run)
