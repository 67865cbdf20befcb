"""Command-line options for one episode, shared by ``roco-env run`` and ``roco-env render``.

(Lives here, not in ``roco_env.cli``, because every module of that package is a
subcommand.)
"""

from __future__ import annotations

import argparse

from roco_env.sweeps.cells import Cell, build_grid, validate_grid
from roco_env.sweeps.text_specs import parse_overrides

DEFAULT_SCENARIO = "crowded_intersection"


def add_episode_options(parser: argparse.ArgumentParser, steps: int) -> None:
    """--scenario, --policy, --noise, --density, --steps, --seed, --set."""
    parser.add_argument("--scenario", default=DEFAULT_SCENARIO,
                        help=f"scenario name or YAML path (default: {DEFAULT_SCENARIO}; "
                        "see `roco-env list`)")
    parser.add_argument("--policy", default="roco",
                        help="policy spec NAME[:KEY=VALUE,...], e.g. roco:tau2=2 (default: roco)")
    parser.add_argument("--noise", type=float, default=0.4,
                        help="pose noise level s: sigma_t = s m, sigma_r = s deg (default: 0.4)")
    parser.add_argument("--density", type=float, default=None,
                        help="traffic density (vehicles per 100 m of lane, parking_lot: stall fill "
                        "ratio 0..1; default: scenario's)")
    parser.add_argument("--steps", type=int, default=steps,
                        help=f"episode length in env steps (default: {steps})")
    parser.add_argument("--seed", type=int, default=0, help="env reset seed (default: 0)")
    parser.add_argument("--set", dest="overrides", action="append", default=[],
                        metavar="KEY=VALUE",
                        help="scenario override, repeatable (e.g. --set detector=ideal --set cavs=3)")


def episode_cell(args: argparse.Namespace) -> Cell:
    """The validated cell the options describe (ValueError naming the bad option)."""
    (cell,) = build_grid([args.scenario], [args.noise], [args.policy], [args.seed], args.steps,
                         densities=[args.density], overrides=parse_overrides(args.overrides))
    validate_grid([cell])
    return cell
