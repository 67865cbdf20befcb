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
The options are the fields of roco_env.stress.study.StressOptions.
"""

from __future__ import annotations

import argparse

from roco_env.cli.render_command import render_episode
from roco_env.stress.space import load_space
from roco_env.stress.stress_report import evaluate_reference, export_worst, section, write_report
from roco_env.stress.study import FLAGS, SearchSettings, check_settings, run_search
from roco_env.sweeps.cells import Cell
from roco_env.sweeps.text_specs import parse_policy_spec


def run(args: argparse.Namespace) -> int:
    options = FLAGS.parse(args)
    space = load_space(options.space)
    all_settings = [
        SearchSettings(out=options.out, policy=parse_policy_spec(policy).label,
                       objective=options.objective, budget=options.budget,
                       seeds=tuple(options.seeds), steps=options.steps, space=space,
                       sampler=options.sampler, seed=options.seed)
        for policy in dict.fromkeys(options.policy)]
    for settings in all_settings:  # every bad setting is refused before any search starts
        check_settings(settings, options.backend, options.workers, options.address)
    sections, summaries = [], []
    for settings in all_settings:
        study = run_search(settings, backend=options.backend, workers=options.workers,
                           address=options.address)
        found = export_worst(settings, study)
        gif = None
        if found and options.gif:
            gif = settings.folder / "worst_episode.gif"
            render_episode(Cell(str(found[0].path), None, settings.policy, settings.seeds[0],
                                settings.steps), gif=gif)
        text, summary = section(settings, study, found, evaluate_reference(settings),
                                None if gif is None else str(gif))
        sections.append(text)
        summaries.append(summary)
    report = write_report(options.out, sections, summaries)
    for summary in summaries:
        print(summary)
    print(f"report: {report}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("stress", help="search for the scenarios where a policy "
                                   "breaks (Optuna)", description=__doc__,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    FLAGS.add_to(parser)
    parser.set_defaults(func=run)
