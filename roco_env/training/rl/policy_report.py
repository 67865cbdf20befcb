"""The report of a ``roco-env train-policy`` run: learning curve PNG, report.json, report.md.

The curve is the learned policy's mean per-step reward on the held-out conditions against
training steps (wall time on the top axis), with one horizontal line per baseline scored on
the same conditions and seeds (:mod:`roco_env.training.rl.evaluate`).
"""

from __future__ import annotations

import json
from dataclasses import asdict
from itertools import cycle
from pathlib import Path
from typing import Any

from roco_env.training.rl.curriculum import eval_conditions
from roco_env.training.rl.ppo import TrainResult

PLOT = "learning_curve.png"


# one colour per baseline line, cycled past the last: every baseline gets its line
COLOURS = ("tab:gray", "tab:brown", "tab:blue", "tab:orange", "tab:green", "tab:red",
           "tab:purple")


def plot_curve(curve: list[dict[str, float]], baselines: dict[str, dict[str, float]],
               action_mode: str, reward: str, path: Path) -> Any:
    """Learned reward vs steps (``curve``: timesteps, wall_s in s, reward) with each of
    ``baselines`` (name -> score with "reward") as a horizontal dashed line, written as a
    PNG to ``path``; returns the matplotlib Figure (Figure API, no pyplot state)."""
    from matplotlib.figure import Figure

    figure = Figure(figsize=(7.5, 4.5))
    axes = figure.add_subplot()
    axes.plot([point["timesteps"] for point in curve], [point["reward"] for point in curve],
              "o-", color="black", label=f"learned ({action_mode})")
    for (name, score), colour in zip(baselines.items(), cycle(COLOURS)):
        axes.axhline(score["reward"], color=colour, linestyle="--", label=name)
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
    """Redraw ``folder``'s learning curve PNG from its saved ``report.json`` (no training);
    returns the Figure."""
    data = json.loads((folder / "report.json").read_text())
    return plot_curve(data["curve"], data["baselines"], data["config"]["action_mode"],
                      data["config"]["reward"], folder / PLOT)


def _wall_axis(curve: list[dict[str, float]]):
    """Steps <-> wall seconds, linear through the last point."""
    rate = curve[-1]["wall_s"] / max(curve[-1]["timesteps"], 1)
    return (lambda x: x * rate, lambda s: s / rate)


def write_report(result: TrainResult, out: Path, command: str, weights: Path,
                 sha256: str) -> dict[str, Any]:
    """Write ``report.json``, ``report.md`` and the PNG into ``out``; returns the JSON data."""
    plot_curve(result.curve, result.baselines, result.config.action_mode,
               result.config.reward, out / PLOT)
    final = result.curve[-1]
    data = {"command": command, "weights": weights.name, "sha256": sha256,
            "config": asdict(result.config), "final": final, "curve": result.curve,
            "baselines": result.baselines,
            "eval_conditions": [asdict(c) for c in eval_conditions(result.config)]}
    (out / "report.json").write_text(json.dumps(data, indent=1))
    rows = [("learned", final)] + list(result.baselines.items())
    table = "\n".join(f"| {name} | {score['reward']:.4f} | {score['ap70']:.4f} |"
                      for name, score in rows)
    (out / "report.md").write_text(
        f"# train-policy report\n\nCommand:\n\n```\n{command}\n```\n\n"
        f"Weights: `{weights.name}` (sha256 `{sha256}`), {final['timesteps']} env steps, "
        f"{final['wall_s']:.0f} s of training and evaluation.\n\n"
        f"Held-out evaluation: scenarios {result.config.scenarios}, noise "
        f"{result.config.eval_noises} (sigma_t m = sigma_r deg), {result.config.eval_seeds} "
        f"seed(s) each, {result.config.episode_steps} steps, Gaussian noise; mean per step.\n\n"
        f"| policy | {result.config.reward} | AP@0.7 |\n|---|---|---|\n{table}\n\n"
        f"![learning curve]({PLOT})\n")
    return data
