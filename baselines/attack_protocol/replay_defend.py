"""Replay the attack protocol's episodes through variants of ``defend`` (docs/attacks.md).

    python baselines/attack_protocol/replay_defend.py --seeds 2-7                # as shipped
    python baselines/attack_protocol/replay_defend.py --seeds 8-11 --attacks "erase 50%" --details
    python baselines/attack_protocol/replay_defend.py --seeds 2-7 --variant "" \\
        --variant "orphan_rate=0.03,sticky=0,own_car_m=0" --attacks "ghosts 5" none

Plays each (scene, attack, seed) of the protocol (both scenes, noise 0.4, the realistic
detector, 1 of 5 agents attacking, ``--steps`` steps) once with ``defend:base=roco``'s env
modes and the all-keep action (nobody rejected), records every agent's aligned observation
and info, and hands them, step by step, to a fresh ``Defend`` per variant and agent (a
variant is defend's parameters as ``key=value,...``; "" = the defaults). Per variant it
prints, pooled over the seeds, each cell's detection (share of (honest ego, step, attacker
slot) rejected) and honest rejections (share of (honest ego, step, honest slot)), the
latter with its spread over the seeds (mean, sd and largest of the per-seed shares);
``--details`` lists every attacker slot missed and every honest collaborator rejected
(seed, step, ego, collaborator, and the test that rejected it).

What a replay is not: the protocol's episodes are played with defend's own actions, and a
rejection makes the gate mode solve the kept collaborators' poses again without the
rejected ones; the recording keeps everyone, so a kept collaborator's pose here is the one
the base aligner found with the liar still in. On the protocol's seeds 0-1 the replay of
defend as of commit 8d56ac5 gave the protocol record's detection within a point on every
attack of both scenes (equal to the printed whole per cent on all but two cells) and
its honest rejections within 0.1 point (docs/attacks.md has the comparison). Use seeds
other than 0-1 (the protocol's) to choose parameters. Nothing is written; the
recordings live in memory, one episode at a time.
"""

from __future__ import annotations

import argparse
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np

from roco_env.policies import make_policy
from roco_env.policies.defend import Defend
from roco_env.policies.spec import parse_assignment
from roco_env.sweeps.attack_protocol import ATTACKS, NOISE, PROTOCOL, SCENES, STEPS
from roco_env.sweeps.cells import build_grid
from roco_env.sweeps.episode import make_env


def record(scene: str, attack: str, seed: int, steps: int) -> list[dict[str, tuple]]:
    """Per step, agent -> (aligned observation, info) of the protocol's episode under
    ``defend:base=roco``'s env modes, every collaborator kept."""
    (cell,) = build_grid([scene], [NOISE], ["defend:base=roco"], [seed], steps,
                         overrides={**PROTOCOL, **SCENES[scene], **ATTACKS[attack]})
    env = make_env(cell, policy=make_policy("defend"))
    observations, infos = env.reset(seed=seed)
    calls = []
    while env.agents and len(calls) < steps:
        calls.append({agent: (observations[agent], infos[agent]) for agent in env.agents})
        keep = {agent: np.zeros(env.config.max_collaborators, dtype=np.int64)
                for agent in env.agents}
        observations, _, _, _, infos = env.step(keep)
    env.close()
    return calls


class Decision(NamedTuple):
    """defend's decision on one collaborator of an honest ego at one step: ``rejected``
    (1) or kept (0), and why (``Defend.last_reasons``: "" when kept)."""

    step: int
    ego: str
    collaborator: str
    attacker: bool
    rejected: int
    reason: str


def decisions(calls: Sequence[Mapping[str, tuple]], params: Mapping[str, object]
              ) -> list[Decision]:
    """defend's decision on every collaborator of every honest ego's step of one recorded
    episode, a fresh ``Defend`` per agent (the attackers' own calls are played, not
    returned)."""
    policies: dict[str, Defend] = {}
    found = []
    for number, step in enumerate(calls):
        for agent, (observation, info) in step.items():
            policy = policies.setdefault(agent, Defend(**params))
            action = policy(observation, info)
            if info["privileged"]["attacker"]:
                continue
            liars = np.asarray(info["privileged"]["collab_attackers"])
            for slot in np.flatnonzero(np.asarray(observation["collab_mask"]) > 0):
                found.append(Decision(number, agent, str(info["collaborators"][slot]),
                                      bool(liars[slot]), int(action[slot]),
                                      policy.last_reasons[slot]))
    return found


def split(found: Sequence[Decision]) -> tuple[list[int], list[int]]:
    """The rejections (1 = rejected) among ``found``: (per attacker slot of an honest ego's
    step, per honest slot)."""
    return ([entry.rejected for entry in found if entry.attacker],
            [entry.rejected for entry in found if not entry.attacker])


def parse_variant(text: str) -> dict[str, object]:
    """``key=value,...`` -> defend's keyword arguments ("" -> none). ``base`` is refused:
    the episodes are recorded behind roco, so another base would be ignored."""
    params = dict(parse_assignment(item, "--variant") for item in text.split(",") if item)
    if "base" in params:
        raise ValueError(f"--variant {text!r}: base is not a variant parameter (the "
                         "episodes are recorded behind roco, defend:base=roco); vary "
                         "defend's tests and thresholds only")
    return params


def parse_seeds(text: str) -> list[int]:
    """``2-7`` (first to last, both included, first <= last) or ``2,3,5``: non-negative
    integers; argparse.ArgumentTypeError naming --seeds otherwise."""
    bad = argparse.ArgumentTypeError(f"--seeds {text!r}: give FIRST-LAST (FIRST <= LAST) or "
                                     "a comma-separated list of non-negative integers, "
                                     "e.g. 2-7 or 2,3,5")
    parts = text.split("-") if "-" in text else text.split(",")
    if not all(part.strip().isdigit() for part in parts) or ("-" in text and len(parts) != 2):
        raise bad
    seeds = [int(part) for part in parts]
    if "-" in text:
        if seeds[0] > seeds[1]:
            raise bad
        return list(range(seeds[0], seeds[1] + 1))
    return list(dict.fromkeys(seeds))  # a seed listed twice is played once


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=parse_seeds, default="2-7",
                        help="e.g. 2-7 or 2,3 (default 2-7)")
    parser.add_argument("--steps", type=int, default=STEPS)
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    parser.add_argument("--attacks", nargs="+", default=list(ATTACKS), choices=list(ATTACKS))
    parser.add_argument("--variant", action="append", default=None,
                        help="defend's parameters, key=value,... (repeatable; default: '')")
    parser.add_argument("--details", action="store_true",
                        help="also list every missed attacker slot and every honest "
                        "collaborator rejected (seed, step, ego, collaborator, reason)")
    args = parser.parse_args(argv)
    variants = {text: parse_variant(text) for text in (args.variant or [""])}
    for params in variants.values():
        Defend(**params)  # a bad parameter fails before anything is played
    # (variant, scene, attack) -> seed -> that episode's decisions
    played: dict[tuple[str, str, str], dict[int, list[Decision]]] = {}
    for scene in args.scenes:
        for attack in args.attacks:
            for seed in args.seeds:
                calls = record(scene, attack, seed, args.steps)
                for text, params in variants.items():
                    played.setdefault((text, scene, attack), {})[seed] = decisions(calls,
                                                                                   params)
    seeds = ",".join(str(seed) for seed in args.seeds)
    print(f"seeds {seeds}, {args.steps} steps: detected % / honest rejected %"
          + (" (per seed: mean, sd, max)" if len(args.seeds) > 1 else ""))
    for text in variants:
        print(f"variant {text or '(defaults)'!r}")
        for scene in args.scenes:
            cells = []
            for attack in args.attacks:
                episodes = played[text, scene, attack]
                found, wrong = split([d for episode in episodes.values() for d in episode])
                detected = f"{100 * np.mean(found):.0f}" if found else "-"
                cells.append(f"{attack}: {detected} / {100 * np.mean(wrong):.1f}"
                             + _spread(episodes))
            print(f"  {scene}: " + " | ".join(cells))
        if args.details:
            for scene in args.scenes:
                for attack in args.attacks:
                    _print_details(scene, attack, played[text, scene, attack])


def _spread(episodes: Mapping[int, Sequence[Decision]]) -> str:
    """The share of honest slots rejected per episode (seed), as " (mean, sd, max)" in
    per cent over the episodes that have honest slots; "" for fewer than two."""
    honest = [split(episode)[1] for episode in episodes.values()]
    shares = 100 * np.array([np.mean(rejected) for rejected in honest if rejected])
    if shares.size < 2:
        return ""
    return f" ({shares.mean():.1f}, {shares.std(ddof=1):.1f}, {shares.max():.1f})"


def _print_details(scene: str, attack: str, episodes: Mapping[int, Sequence[Decision]]
                   ) -> None:
    """One line per missed attacker slot and per honest collaborator rejected."""
    for seed, episode in episodes.items():
        for d in episode:
            if d.attacker and not d.rejected:
                print(f"    {scene} | {attack} | seed {seed} step {d.step}: {d.ego} missed "
                      f"the attacker {d.collaborator}")
            elif not d.attacker and d.rejected:
                print(f"    {scene} | {attack} | seed {seed} step {d.step}: {d.ego} rejected "
                      f"the honest {d.collaborator} ({d.reason})")


if __name__ == "__main__":
    main()
