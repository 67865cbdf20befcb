"""The report of a ``roco-env train-policy`` run: learning curve PNG, report.json, report.md.

The curve is the learned policy's mean per-step reward on the held-out conditions against
training steps (wall time on the top axis), with one horizontal line per baseline scored on
the same conditions and seeds (:mod:`roco_env.training.rl.evaluate`).
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import Any

from roco_env.training.rl.curriculum import eval_conditions
from roco_env.training.rl.ppo import TrainResult

PLOT = "learning_curve.png"


def plot_curve(result: TrainResult, path: Path) -> None:
    """Learned reward vs steps with the baselines as horizontal lines (Figure API)."""
    from matplotlib.figure import Figure

    figure = Figure(figsize=(7.5, 4.5))
    axes = figure.add_subplot()
    steps = [point["timesteps"] for point in result.curve]
    axes.plot(steps, [point["reward"] for point in result.curve], "o-", color="black",
              label=f"learned ({result.config.action_mode})")
    colours = ("tab:gray", "tab:brown", "tab:blue", "tab:orange", "tab:green", "tab:red")
    for (name, score), colour in zip(result.baselines.items(), colours, strict=False):
        axes.axhline(score["reward"], color=colour, linestyle="--", label=name)
    axes.set_xlabel("training env steps")
    axes.set_ylabel(f"mean per-step {result.config.reward} (held-out)")
    if result.curve and result.curve[-1]["timesteps"] > 0:
        top = axes.secondary_xaxis("top", functions=_wall_axis(result.curve))
        top.set_xlabel("wall time (s)")
    axes.legend(fontsize=8, loc="best")
    axes.grid(alpha=0.3)
    figure.tight_layout()
    figure.savefig(path, dpi=110)


def _wall_axis(curve: list[dict[str, float]]):
    """Steps <-> wall seconds, linear through the last point."""
    rate = curve[-1]["wall_s"] / max(curve[-1]["timesteps"], 1)
    return (lambda x: x * rate, lambda s: s / rate)


def write_report(result: TrainResult, out: Path, command: str, weights: Path,
                 sha256: str) -> dict[str, Any]:
    """Write ``report.json``, ``report.md`` and the PNG into ``out``; returns the JSON data."""
    plot_curve(result, out / PLOT)
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
