"""PNG plots of summary rows (matplotlib Figure API: no pyplot, no display, no global backend).

* AP@0.7 vs noise level, one line per policy, one panel per scenario/density;
* AP@0.7 vs density, one line per policy, one panel per scenario/noise level;
* relative-pose-error distribution without and with correction (the paper's
  Figure 7 analogue): density histograms of translation (m) and rotation (deg)
  error, one row of panels per noise level.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from roco_env.sweeps.aggregate import SummaryRow
from roco_env.sweeps.tables import density_label, noise_label

MAX_NOISE_ROWS = 4  # Figure-7 panels: at most this many noise levels (the highest ones)


def _panels(count: int, width: float = 4.5, height: float = 3.4, columns: int = 3):
    ncols = min(columns, count)
    nrows = -(-count // ncols)
    fig = Figure(figsize=(width * ncols, height * nrows))
    axes = fig.subplots(nrows, ncols, squeeze=False)
    for ax in axes.flat[count:]:
        ax.set_visible(False)
    return fig, list(axes.flat)


def _line_plot(rows: Sequence[SummaryRow], path: Path, panel_of: Callable[[SummaryRow], tuple],
               panel_title: Callable[[tuple], str], x_of: Callable[[SummaryRow], float],
               x_label: str) -> Path:
    panels: dict[tuple, list[SummaryRow]] = {}
    for row in rows:
        panels.setdefault(panel_of(row), []).append(row)
    fig, axes = _panels(len(panels))
    for ax, (panel, members) in zip(axes, panels.items(), strict=False):
        for policy in dict.fromkeys(r.policy for r in members):
            line = sorted((x_of(r), 100.0 * r.metrics.get("ap70", np.nan))
                          for r in members if r.policy == policy and r.seeds)
            if line:
                xs, ys = zip(*line, strict=True)
                ax.plot(xs, ys, marker="o", label=policy)
        ax.set_title(panel_title(panel), fontsize=9)
        ax.set_xlabel(x_label)
        ax.set_ylabel("AP@0.7 (%)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path


def ap_vs_noise(rows: Sequence[SummaryRow], path: Path) -> Path:
    return _line_plot(
        rows, path, lambda r: (r.scenario, r.density),
        lambda p: f"{p[0]} (density {density_label(p[1])})", lambda r: r.noise,
        "noise level sigma_t / sigma_r (m / deg)")


def ap_vs_density(rows: Sequence[SummaryRow], path: Path) -> Path:
    """Only meaningful with >= 2 densities per panel (the caller decides)."""
    return _line_plot(
        [r for r in rows if r.density is not None], path, lambda r: (r.scenario, r.noise),
        lambda p: f"{p[0]} (noise {noise_label(p[1])})", lambda r: float(r.density),
        "traffic density (vehicles / 100 m of lane; parking_lot: fill ratio)")


def rpe_distribution(rows: Sequence[SummaryRow], path: Path) -> Path:
    """Figure 7 analogue; 'no correction' = the first policy's before-errors (same for all)."""
    noises = sorted({r.noise for r in rows if r.noise > 0 and r.after.size})[-MAX_NOISE_ROWS:]
    if not noises:
        noises = sorted({r.noise for r in rows if r.after.size})[-1:]
    fig = Figure(figsize=(10, 3.2 * max(len(noises), 1)))
    axes = fig.subplots(max(len(noises), 1), 2, squeeze=False)
    for axes_row, noise in zip(axes, noises, strict=False):
        members = [r for r in rows if r.noise == noise and r.after.size]
        by_policy = {p: [r for r in members if r.policy == p]
                     for p in dict.fromkeys(r.policy for r in members)}
        before = np.concatenate([r.before for r in next(iter(by_policy.values()))])
        for column, (ax, unit) in enumerate(zip(axes_row, ("m", "deg"), strict=True)):
            top = max(float(np.percentile(before[:, column], 99)), 1e-3) if before.size else 1.0
            bins = np.linspace(0.0, top, 40)
            ax.hist(np.clip(before[:, column], 0, top), bins=bins, density=True,
                    histtype="step", linewidth=2, color="C0", label="no correction")
            corrected = [p for p in by_policy if p != "identity"]
            for colour, policy in enumerate(corrected, start=1):
                after = np.concatenate([r.after[:, column] for r in by_policy[policy]])
                ax.hist(np.clip(after, 0, top), bins=bins, density=True, histtype="step",
                        linestyle="--", color=f"C{colour}", label=policy)
            kind = "translation" if column == 0 else "rotation"
            ax.set_title(f"{kind} error, noise {noise_label(noise)}", fontsize=9)
            ax.set_xlabel(f"relative pose error ({unit})")
            ax.set_ylabel("density")
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path
