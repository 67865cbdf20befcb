"""The report of a ``roco-env train-policy`` run: learning curve PNG, report.json, report.md.

The curve is the learned policy's mean per-step reward on the held-out conditions against
training steps (wall time on the top axis), with one horizontal line per baseline scored on
the same conditions and seeds (:mod:`roco_env.training.rl.evaluate`). A guarded run's
baseline :data:`~roco_env.training.rl.evaluate.RULE` (the guard's rule alone) is labelled
with the fixed policy spec it plays. report.md and the PNG are drawn from report.json
alone (:func:`replot` redraws them from a saved one, an older report's rule key mapped).
"""

from __future__ import annotations

import json
from dataclasses import asdict
from itertools import cycle
from pathlib import Path
from typing import Any

from roco_env.training.rl.config import build_config
from roco_env.training.rl.curriculum import eval_conditions
from roco_env.training.rl.evaluate import RULE, rule_spec, with_rule_key
from roco_env.training.rl.ppo import TrainResult

PLOT = "learning_curve.png"


# one colour per baseline line, cycled past the last: every baseline gets its line
COLOURS = ("tab:gray", "tab:brown", "tab:blue", "tab:orange", "tab:green", "tab:red",
           "tab:purple")


def plot_curve(curve: list[dict[str, float]], baselines: dict[str, dict[str, float]],
               action_mode: str, reward: str, path: Path, rule: str = "") -> Any:
    """Learned reward vs steps (``curve``: timesteps, wall_s in s, reward) with each of
    ``baselines`` (name -> score with "reward") as a horizontal dashed line, written as a
    PNG to ``path``; ``rule``: the spec the :data:`RULE` line is labelled with beside its
    name. Returns the matplotlib Figure (Figure API, no pyplot state)."""
    from matplotlib.figure import Figure

    figure = Figure(figsize=(7.5, 4.5))
    axes = figure.add_subplot()
    axes.plot([point["timesteps"] for point in curve], [point["reward"] for point in curve],
              "o-", color="black", label=f"learned ({action_mode})")
    for (name, score), colour in zip(baselines.items(), cycle(COLOURS)):
        axes.axhline(score["reward"], color=colour, linestyle="--",
                     label=_label(name, rule))
    axes.set_xlabel("training env steps")
    axes.set_ylabel(f"mean per-step {reward} (held-out)")
    if curve and curve[-1]["timesteps"] > 0:
        top = axes.secondary_xaxis("top", functions=_wall_axis(curve))
        top.set_xlabel("wall time (s)")
    axes.legend(fontsize=8, loc="best")
    axes.grid(alpha=0.3)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    return figure


def replot(folder: Path) -> Any:
    """Redraw ``folder``'s learning curve PNG and report.md from its saved ``report.json``
    (no training); returns the Figure."""
    return render(folder, json.loads((folder / "report.json").read_text()))


def _label(name: str, rule: str) -> str:
    return f"{name}: {rule}" if name == RULE and rule else name


def _wall_axis(curve: list[dict[str, float]]):
    """Steps <-> wall seconds, linear through the last point."""
    rate = curve[-1]["wall_s"] / max(curve[-1]["timesteps"], 1)
    return (lambda x: x * rate, lambda s: s / rate)


def write_report(result: TrainResult, out: Path, command: str, weights: Path,
                 sha256: str) -> dict[str, Any]:
    """Write ``report.json``, ``report.md`` and the PNG into ``out``; returns the JSON data."""
    data = {"command": command, "weights": weights.name, "sha256": sha256,
            "config": asdict(result.config), "final": result.curve[-1],
            "curve": result.curve, "baselines": result.baselines,
            "eval_conditions": [asdict(c) for c in eval_conditions(result.config)]}
    (out / "report.json").write_text(json.dumps(data, indent=1))
    render(out, data)
    return data


def render(out: Path, data: dict[str, Any]) -> Any:
    """Write report.md and the PNG into ``out`` from report.json's ``data``; returns the
    PNG's Figure."""
    config = build_config(data["config"])
    baselines = with_rule_key(data["baselines"])
    rule = rule_spec(config) if RULE in baselines else ""
    figure = plot_curve(data["curve"], baselines, config.action_mode, config.reward,
                        out / PLOT, rule)
    final = data["final"]
    rows = [("learned", final)] + list(baselines.items())
    table = "\n".join(f"| {name}{f' (`{rule}`)' if name == RULE else ''} | "
                      f"{score['reward']:.4f} | {score['ap70']:.4f} |"
                      for name, score in rows)
    note = (f"`{RULE}`: the guard's rule alone, the fixed policy `{rule}` played in the "
            "training env (what the network adds is its score minus this row).\n\n"
            if rule else "")
    (out / "report.md").write_text(
        f"# train-policy report\n\nCommand:\n\n```\n{data['command']}\n```\n\n"
        f"Weights: `{data['weights']}` (sha256 `{data['sha256']}`), {final['timesteps']} env "
        f"steps, {final['wall_s']:.0f} s of training and evaluation.\n\n"
        f"Held-out evaluation: scenarios {config.scenarios}, noise "
        f"{config.eval_noises} (sigma_t m = sigma_r deg), {config.eval_seeds} "
        f"seed(s) each, {config.episode_steps} steps, Gaussian noise; mean per step.\n\n"
        f"| policy | {config.reward} | AP@0.7 |\n|---|---|---|\n{table}\n\n{note}"
        f"![learning curve]({PLOT})\n")
    return figure
