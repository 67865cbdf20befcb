"""The attack protocol: every scripted attack against every aligner, alone and behind
``defend`` (docs/attacks.md; the recorded run and its reading: baselines/attack_protocol).

    python -m roco_env.sweeps.attack_protocol                # into baselines/results/attack_protocol
    python -m roco_env.sweeps.attack_protocol --seeds 1 --steps 3 --out runs/attack_smoke

One agent of five attacks (drawn per episode from the seed) on urban_intersection and
v2xset_like (4 CAVs + 1 RSU), noise 0.4 (sigma_t 0.4 m, sigma_r 0.4 deg on every agent),
realistic detector, late fusion; the references: no fusion (each ego's own boxes), the
oracle and ``privileged_gate:base=roco`` (the attacker rejected from the truth). Each cell
is scored by
:func:`roco_env.sweeps.attack.run_attack_cell` against its clean twin; ``report.md`` holds
the attack tables (AP@0.7 under attack and clean, attack success, detection rate, honest
rejections) and the targets of ``defend:base=roco``.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from roco_env.sweeps.attack import ATTACK_PREFIX, run_attack_cell
from roco_env.sweeps.backends import BACKENDS
from roco_env.sweeps.cells import Cell, build_grid, validate_grid
from roco_env.sweeps.sweep import run_sweep
from roco_env.sweeps.text_specs import Scalar

NOISE = 0.4
SPOOF, GHOST = "pose_spoof", "ghost"
# label -> the attack.* overrides (empty: no attack, the clean row)
ATTACKS: dict[str, dict[str, Scalar]] = {
    "none": {},
    "spoof 1 m": {"attack.kind": SPOOF, "attack.params.offset_m": 1.0},
    "spoof 3 m": {"attack.kind": SPOOF, "attack.params.offset_m": 3.0},
    "spoof 10 m": {"attack.kind": SPOOF, "attack.params.offset_m": 10.0},
    "spoof 3 m consistent": {"attack.kind": SPOOF, "attack.params.offset_m": 3.0,
                             "attack.params.consistent": True},
    "spoof 10 m drifting in 1 s": {"attack.kind": SPOOF, "attack.params.offset_m": 10.0,
                                   "attack.params.drift": 1.0},
    "ghosts 5": {"attack.kind": GHOST, "attack.params.n_ghost": 5},
    "ghosts 20": {"attack.kind": GHOST, "attack.params.n_ghost": 20},
    "ghosts 20 lanes": {"attack.kind": GHOST, "attack.params.n_ghost": 20,
                        "attack.params.placement": "lanes"},
    "ghosts 20 aliasing": {"attack.kind": GHOST, "attack.params.n_ghost": 20,
                           "attack.params.placement": "aliasing"},
    "erase 50%": {"attack.kind": "erase", "attack.params.share": 0.5},
}
# scenario -> its overrides: five agents each
SCENES: dict[str, dict[str, Scalar]] = {"urban_intersection": {}, "v2xset_like": {"cavs": 4}}
ALIGNERS = ("identity", "coalign", "roco", "roco_antialias")
# The references: each ego's own boxes alone (identity with fusion none, whatever is sent),
# the true poses, and the perfect rejection of the attacker behind roco.
NO_FUSION = "no_fusion"
POLICIES = (NO_FUSION, *ALIGNERS, "oracle", *(f"defend:base={name}" for name in ALIGNERS),
            "privileged_gate:base=roco")
PROTOCOL: dict[str, Scalar] = {"detector": "realistic", "noise.perturb_ego": True}
SEEDS, STEPS = 2, 10
# The targets of defend:base=roco (docs/attacks.md): AP@0.7 points kept, detection, honest
# rejections, the cost without an attacker against roco.
TARGET_AP_POINTS, TARGET_DETECTION, TARGET_HONEST, TARGET_CLEAN_COST = 2.0, 0.95, 0.02, 0.5


def protocol_cells(seeds: int = SEEDS, steps: int = STEPS,
                   policies: Sequence[str] = POLICIES) -> list[Cell]:
    """Every (scene, attack, policy, seed) cell of the protocol; :data:`NO_FUSION` is
    ``identity`` with ``fusion: none``."""
    aligned = [policy for policy in policies if policy != NO_FUSION]
    runs = [(aligned, {})] if aligned else []
    if NO_FUSION in policies:
        runs.append((["identity"], {"fusion": "none"}))
    return [cell for scene, extra in SCENES.items() for attack in ATTACKS.values()
            for chosen, fusion in runs
            for cell in build_grid([scene], [NOISE], chosen, list(range(seeds)), steps,
                                   overrides={**PROTOCOL, **extra, **attack, **fusion})]


def policy_label(cell: dict) -> str:
    """The :data:`POLICIES` entry of a record's cell (:data:`NO_FUSION` for fusion none)."""
    return NO_FUSION if cell["overrides"].get("fusion") == "none" else cell["policy"]


def attack_label(cell: dict) -> str:
    """The :data:`ATTACKS` label of a record's cell (its ``attack.*`` overrides)."""
    given = {k: v for k, v in cell["overrides"].items() if k.startswith(ATTACK_PREFIX)}
    return next((label for label, attack in ATTACKS.items() if attack == given),
                ", ".join(f"{k}={v}" for k, v in sorted(given.items())))


def summary(records: Sequence[dict]) -> dict[tuple[str, str, str], dict[str, float]]:
    """(scenario, attack label, policy) -> each metric's mean over the ok seeds."""
    groups: dict[tuple[str, str, str], list[dict]] = {}
    for record in records:
        if record["status"] == "ok":
            cell = record["cell"]
            key = (cell["scenario"], attack_label(cell), policy_label(cell))
            groups.setdefault(key, []).append(record["metrics"])
    return {key: {name: float(np.nanmean([np.nan if m.get(name) is None else m[name]
                                          for m in rows]))
                  for name in rows[0]} for key, rows in groups.items()}


def _table(rows: dict, scenario: str, policies: Sequence[str], text) -> list[str]:
    head = ["| attack | " + " | ".join(f"`{p}`" for p in policies) + " |",
            "|---" * (len(policies) + 1) + "|"]
    body = []
    for label in ATTACKS:
        cells = [text(rows.get((scenario, label, policy))) for policy in policies]
        body.append(f"| {label} | " + " | ".join(cells) + " |")
    return head + body


def _share(metrics: dict | None, name: str) -> str:
    if metrics is None or np.isnan(metrics.get(name, np.nan)):
        return "-"
    return f"{100 * metrics[name]:.0f}%"


def _ap_pair(metrics: dict | None) -> str:
    if metrics is None:
        return "-"
    return f"{100 * metrics['ap70']:.1f} / {100 * metrics['ap70_clean']:.1f}"


def targets(rows: dict, scenario: str) -> list[str]:
    """The targets of ``defend:base=roco`` per attack: AP@0.7 kept within 2 points of the
    clean episode, detection >= 95%, honest rejections <= 2%; without an attacker its cost
    against roco <= 0.5 points."""
    lines = ["| attack | AP@0.7 lost (points) | detected | honest rejected | met |",
             "|---|---|---|---|---|"]
    for label in ATTACKS:
        m = rows.get((scenario, label, "defend:base=roco"))
        if m is None or label == "none":
            continue
        lost = round(100 * (m["ap70_clean"] - m["ap70"]), 1)  # as printed
        met = lost <= TARGET_AP_POINTS and m["detection_rate"] >= TARGET_DETECTION \
            and m["honest_rejected"] <= TARGET_HONEST
        lines.append(f"| {label} | {lost:.1f} | {_share(m, 'detection_rate')} | "
                     f"{_share(m, 'honest_rejected')} | {'yes' if met else 'no'} |")
    clean, roco = rows.get((scenario, "none", "defend:base=roco")), \
        rows.get((scenario, "none", "roco"))
    if clean is not None and roco is not None:
        cost = round(100 * (roco["ap70"] - clean["ap70"]), 1)
        met = cost <= TARGET_CLEAN_COST and clean["honest_rejected"] <= TARGET_HONEST
        lines.append(f"| none: cost against roco | {cost:.1f} | - | "
                     f"{_share(clean, 'honest_rejected')} | {'yes' if met else 'no'} |")
    return lines


def render(records: Sequence[dict], title: str = "Attack protocol") -> str:
    """The attack tables of ``records`` as Markdown."""
    rows = summary(records)
    found = {policy for _, _, policy in rows}
    policies = [p for p in POLICIES if p in found] + sorted(found - set(POLICIES))
    seeds = sorted({r["cell"]["seed"] for r in records})
    steps = sorted({r["cell"]["steps"] for r in records})
    failed = [r for r in records if r["status"] != "ok"]
    parts = [f"# {title}", "",
             f"1 of 5 agents attacks (drawn per episode), noise {NOISE} (sigma_t m / sigma_r "
             f"deg), realistic detector, late fusion; seeds {seeds}, {steps} steps each; "
             "mean over seeds. Scored over the honest egos; clean = the same episode without "
             "the attack, same policy.", ""]
    for scenario in SCENES:
        if not any(key[0] == scenario for key in rows):
            continue
        parts += [f"## {scenario}", "", "### AP@0.7 (%) under attack / clean", ""]
        parts += _table(rows, scenario, policies, _ap_pair)
        for name, heading in (("attack_success", "Attack success (ego-steps losing > 5 "
                               "points of AP@0.7)"),
                              ("detection_rate", "Detection rate (attacker slots rejected)"),
                              ("honest_rejected", "Honest collaborators rejected")):
            parts += ["", f"### {heading}", ""]
            parts += _table(rows, scenario, policies, lambda m, n=name: _share(m, n))
        parts += ["", "### Targets of `defend:base=roco`", ""] + targets(rows, scenario) + [""]
    if failed:
        parts += ["## Failed cells", ""] + [f"- `{r['key']}`: {r.get('error')}" for r in failed]
    return "\n".join(parts) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m roco_env.sweeps.attack_protocol",
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=SEEDS, help="seeds per setting")
    parser.add_argument("--steps", type=int, default=STEPS, help="steps per episode")
    parser.add_argument("--policies", nargs="+", default=list(POLICIES), metavar="SPEC")
    parser.add_argument("--out", default="baselines/results/attack_protocol")
    parser.add_argument("--backend", default="local", choices=BACKENDS)
    parser.add_argument("--workers", type=int, default=None, help="default: all cores")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    try:
        if args.seeds < 1 or args.steps < 1:
            raise ValueError(f"--seeds and --steps must be >= 1; got {args.seeds}, {args.steps}")
        cells = protocol_cells(args.seeds, args.steps, args.policies)
        validate_grid(cells)
    except ValueError as exc:
        print(f"{parser.prog}: error: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    outcome = run_sweep(cells, out / "results.jsonl", backend=args.backend,
                        workers=args.workers, cell_fn=run_attack_cell,
                        progress=not args.quiet)
    markdown = render(outcome.records)
    (out / "report.md").write_text(markdown, encoding="utf-8")
    print(markdown)
    return 1 if outcome.failed else 0


if __name__ == "__main__":
    sys.exit(main())
