"""``roco-env list``: the scenarios and alignment policies available."""

from __future__ import annotations

import argparse

from roco_env.policies import available_policies, make_policy
from roco_env.scenario import list_scenarios, load_scenario


def _scenario_lines() -> list[str]:
    lines = []
    for name in list_scenarios():
        try:
            description = load_scenario(name).description.strip().splitlines()
            summary = description[0] if description else ""
        except ValueError as exc:  # a broken user file must not hide the others
            summary = f"(invalid: {exc})"
        lines.append(f"  {name:<28} {summary}".rstrip())
    return lines


def _policy_lines() -> list[str]:
    """One line per policy; stateful ones say what they keep (every instance can be shared
    by all agents of an env: state is keyed by the ego)."""
    lines = []
    for name in available_policies():
        try:
            state = make_policy(name).keeps_state
        except (ValueError, TypeError) as exc:  # a broken plug-in must not hide the others
            lines.append(f"  {name:<28} (cannot build: {exc})")
            continue
        lines.append(f"  {name:<28} stateful: keeps state {state}; pass infos, and one "
                     "instance serves all agents" if state else f"  {name}")
    return lines


def run(args: argparse.Namespace) -> int:
    if args.what in ("all", "scenarios"):
        print("scenarios:")
        print("\n".join(_scenario_lines()) or "  (none found)")
    if args.what in ("all", "policies"):
        print("policies (spec NAME[:KEY=VALUE,...], e.g. roco:tau2=2, or my_pkg.module:factory):")
        print("\n".join(_policy_lines()))
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "list", help="list scenarios and policies",
        description="List the scenario names (YAML files in scenarios/ and $ROCO_ENV_SCENARIOS) "
        "and the registered alignment policies.")
    parser.add_argument("what", nargs="?", default="all", choices=("all", "scenarios", "policies"),
                        help="what to list (default: all)")
    parser.set_defaults(func=run)
