"""The training report of ``roco-env train-detector``: loss curves (PNG), JSON and Markdown."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from roco_env.training.train import TrainResult

__all__ = ["loss_curves_figure", "write_report"]


def _smooth(values: list[float], window: int) -> np.ndarray:
    """Trailing moving average (window steps, shorter at the start)."""
    arr = np.asarray(values, dtype=float)
    cumsum = np.concatenate([[0.0], np.cumsum(arr)])
    idx = np.arange(1, arr.size + 1)
    lo = np.maximum(idx - window, 0)
    return (cumsum[idx] - cumsum[lo]) / (idx - lo)


def loss_curves_figure(history: dict[str, list[float]]) -> Figure:
    """Per-step training losses (moving average): the total, single-agent and fused losses,
    then the single-agent terms. Linear y axes: the Gaussian NLL term (and so the
    single-agent and total losses) goes negative, which a log axis would drop."""
    window = max(1, len(history["total"]) // 30)
    fig = Figure(figsize=(11, 4))
    axes = fig.subplots(1, 2)
    for name in ("total", "single", "fused"):
        axes[0].plot(_smooth(history[name], window), label=name)
    axes[0].set(title=f"loss (moving average over {window} steps)", xlabel="training step",
                ylabel="loss")
    for name in ("heatmap", "offset", "size", "yaw", "nll"):
        axes[1].plot(_smooth(history[name], window), label=name)
    axes[1].set(title="single-agent loss terms (same average)", xlabel="training step",
                ylabel="loss term")
    for ax in axes:
        ax.axhline(0.0, color="0.5", linewidth=0.8)
        ax.legend()
        ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig


def write_report(result: TrainResult, out: Path, command: str, weights_sha256: str,
                 init_sha256: str | None = None) -> None:
    """loss_curves.png, loss_history.json (the per-step losses the picture draws, so it can
    be redrawn), report.json and report.md in ``out``; init_sha256: of the weights file a
    fine-tuning run started from."""
    loss_curves_figure(result.history).savefig(out / "loss_curves.png", dpi=90)
    (out / "loss_history.json").write_text(json.dumps(result.history) + "\n")
    init = {} if init_sha256 is None else {"init_sha256": init_sha256}
    summary = {"command": command, "weights_sha256": weights_sha256, **init,
               **result.summary()}
    (out / "report.json").write_text(json.dumps(summary, indent=2) + "\n")
    val = result.validation
    rows = "\n".join(f"| {k} | {v:.3f} |" for k, v in val.items())
    cfg = result.config
    start = ("random initialisation" if cfg.init is None else
             f"`{cfg.init}` (sha256 `{init_sha256}`), "
             + ("detector frozen, only the fusion gate trained" if not cfg.train_detector
                else "encoder frozen" if not cfg.train_encoder else "whole network trained"))
    fused = ("the detector grid" if cfg.fused_x_range is None and cfg.fused_y_range is None
             else f"a canvas of x {list(cfg.fused_canvas.x_range)} m, "
             f"y {list(cfg.fused_canvas.y_range)} m (fused validation AP decoded on it too)")
    (out / "report.md").write_text(
        "# Learned BEV detector: training report\n\n"
        f"Command: `{command}`\n\n"
        f"Seed {cfg.seed}, {cfg.threads} CPU thread(s), device {cfg.device}; "
        f"{cfg.train_scenes} training scenes from {', '.join(cfg.scenarios)}; "
        f"{cfg.steps} steps of {cfg.scenes_per_step} scenes; fused-loss pose noise "
        f"{cfg.pose_sigma_t} m / {cfg.pose_sigma_r} deg; "
        f"{summary['parameters']} parameters; {result.seconds:.0f} s.\n\n"
        f"Started from {start}; fusion {cfg.fusion}; fused loss decoded on {fused}; warp "
        f"augmentation {cfg.warp_augment}.\n\n"
        f"Weights sha256: `{weights_sha256}`\n\n"
        f"Validation ({cfg.val_scenes} held-out scenes of {', '.join(cfg.val_scenarios)}, "
        "the environment's ground truth and AP protocol):\n\n"
        "| metric | value |\n|---|---|\n" + rows + "\n\n![loss curves](loss_curves.png)\n")
