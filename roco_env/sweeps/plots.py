"""PNG plots of summary rows (matplotlib Figure API: no pyplot, no display, no global backend).

* AP@0.7 vs noise level, one line per policy, one panel per scenario/density;
* AP@0.7 vs density, one line per policy, one panel per scenario/noise level;
  panels of both share their y axis, so heights compare across panels;
* AP@0.7 vs a grid axis (any scenario field a sweep varies), one line per policy, one
  panel per scenario, density, noise level and the other overrides; numbers on a linear
  axis (logarithmic when they are all > 0 and span two decades or more), other values
  (names, null) as evenly spaced categories;
* relative-pose-error distribution without and with correction (the paper's
  Figure 7 analogue): histograms of translation (m) and rotation (deg) error, one
  row of panels per noise level. Bins are log-spaced and span every sample (no
  tail folded into a last bin, so failures stay visible far right); a bar is the
  share (%) of a policy's pairs in it. Errors below the samples' resolution
  (0.001 m / deg, i.e. stored as 0: the oracle's) cannot sit on a log axis and
  are counted in the legend instead of drawn as a spike.

Each ``*_figure`` function returns the Figure; the plain names save it as PNG.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from roco_env.sweeps.aggregate import SummaryRow
from roco_env.sweeps.episode import SAMPLE_DECIMALS
from roco_env.sweeps.tables import axis_label, density_label, is_number, noise_label, value_order

MAX_NOISE_ROWS = 4  # Figure-7 panels: at most this many noise levels (the highest ones)
RPE_BINS = 40  # log-spaced histogram bins from the resolution to the largest error
RPE_FLOOR = 10.0 ** -SAMPLE_DECIMALS  # m / deg: smaller errors are stored as 0
DPI = 110


def _panels(count: int, width: float = 4.5, height: float = 3.4, columns: int = 3):
    """A grid of ``count`` panels sharing their y axis (unused grid cells hidden)."""
    ncols = min(columns, count)
    nrows = -(-count // ncols)
    fig = Figure(figsize=(width * ncols, height * nrows))
    axes = fig.subplots(nrows, ncols, squeeze=False, sharey=True)
    for ax in axes.flat[count:]:
        ax.set_visible(False)
    return fig, list(axes.flat)


def _save(fig: Figure, path: Path) -> Path:
    fig.savefig(path, dpi=DPI)
    return path


def _line_figure(rows: Sequence[SummaryRow], panel_of: Callable[[SummaryRow], tuple],
                 panel_title: Callable[[tuple], str], x_of: Callable[[SummaryRow], float],
                 x_label: str) -> Figure:
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
        ax.yaxis.set_tick_params(labelleft=True)  # sharey hides them on inner panels
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def ap_vs_noise_figure(rows: Sequence[SummaryRow]) -> Figure:
    return _line_figure(
        rows, lambda r: (r.scenario, r.density),
        lambda p: f"{p[0]} (density {density_label(p[1])})", lambda r: r.noise,
        "noise level sigma_t / sigma_r (m / deg)")


def ap_vs_noise(rows: Sequence[SummaryRow], path: Path) -> Path:
    return _save(ap_vs_noise_figure(rows), path)


def ap_vs_density_figure(rows: Sequence[SummaryRow]) -> Figure:
    """Only meaningful with >= 2 densities per panel (the caller decides)."""
    return _line_figure(
        [r for r in rows if r.density is not None], lambda r: (r.scenario, r.noise),
        lambda p: f"{p[0]} (noise {noise_label(p[1])})", lambda r: float(r.density),
        "traffic density\n(vehicles per 100 m of lane; parking_lot: stall fill ratio)")


def ap_vs_density(rows: Sequence[SummaryRow], path: Path) -> Path:
    return _save(ap_vs_density_figure(rows), path)


def axis_plot_name(axis: str) -> str:
    """The file name of the plot of AP@0.7 against grid axis ``axis``."""
    return "ap70_vs_" + "".join(c if c.isalnum() else "_" for c in axis) + ".png"


def ap_vs_axis_figure(rows: Sequence[SummaryRow], axis: str) -> Figure:
    """AP@0.7 against the values of override ``axis``."""
    values = sorted({axis_label(r.overrides.get(axis)): r.overrides.get(axis)
                     for r in rows}.values(), key=value_order)
    numeric = all(is_number(v) for v in values)
    position = {axis_label(v): float(v) if numeric else float(k) for k, v in enumerate(values)}
    fig = _line_figure(
        rows, lambda r: (r.scenario, r.density, r.noise,
                         tuple((k, axis_label(v)) for k, v in r.overrides.items() if k != axis)),
        lambda p: ", ".join([p[0], f"density {density_label(p[1])}", f"noise {noise_label(p[2])}",
                             *(f"{k}={v}" for k, v in p[3])]),
        lambda r: position[axis_label(r.overrides.get(axis))], axis)
    for ax in fig.axes:
        if numeric and min(values) > 0 and max(values) >= 100 * min(values):
            ax.set_xscale("log")
        elif not numeric:
            ax.set_xticks(list(position.values()), list(position))
    return fig


def ap_vs_axis(rows: Sequence[SummaryRow], axis: str, path: Path) -> Path:
    return _save(ap_vs_axis_figure(rows, axis), path)


def _error_histogram(ax: Axes, errors: np.ndarray, bins: np.ndarray, unit: str, label: str,
                     **style) -> None:
    """Step histogram of ``errors`` on the log-spaced ``bins`` as % of all of them; the
    share below RPE_FLOOR (not drawable on a log axis) goes into the legend label."""
    below = float(np.mean(errors < RPE_FLOOR)) if errors.size else 0.0
    if below > 0:
        label += f" ({100 * below:.3g}% < {RPE_FLOOR:g} {unit})"
    weights = np.full(errors.size, 100.0 / max(errors.size, 1))
    ax.hist(errors, bins=bins, weights=weights, histtype="step", label=label, **style)


def rpe_distribution_figure(rows: Sequence[SummaryRow]) -> Figure:
    """Figure 7 analogue; 'no correction' = the first policy's before-errors (same for all)."""
    noises = sorted({r.noise for r in rows if r.noise > 0 and r.after.size})[-MAX_NOISE_ROWS:]
    if not noises:
        noises = sorted({r.noise for r in rows if r.after.size})[-1:]
    fig = Figure(figsize=(10, 3.2 * max(len(noises), 1) + 0.4))
    axes = fig.subplots(max(len(noises), 1), 2, squeeze=False)
    for axes_row, noise in zip(axes, noises, strict=False):
        members = [r for r in rows if r.noise == noise and r.after.size]
        by_policy = {p: [r for r in members if r.policy == p]
                     for p in dict.fromkeys(r.policy for r in members)}
        before = np.concatenate([r.before for r in next(iter(by_policy.values()))])
        corrected = {p: np.concatenate([r.after for r in by_policy[p]])
                     for p in by_policy if p != "identity"}
        for column, (ax, unit) in enumerate(zip(axes_row, ("m", "deg"), strict=True)):
            top = max([float(before[:, column].max(initial=0.0)),
                       *(float(after[:, column].max(initial=0.0))
                         for after in corrected.values()), 10 * RPE_FLOOR])
            bins = np.geomspace(RPE_FLOOR, top, RPE_BINS + 1)
            _error_histogram(ax, before[:, column], bins, unit, "no correction", linewidth=2,
                             color="C0")
            for colour, (policy, after) in enumerate(corrected.items(), start=1):
                _error_histogram(ax, after[:, column], bins, unit, policy, linestyle="--",
                                 color=f"C{colour}")
            kind = "translation" if column == 0 else "rotation"
            ax.set_title(f"{kind} error, noise {noise_label(noise)}", fontsize=9)
            ax.set_xscale("log")
            ax.set_xlim(RPE_FLOOR, top)
            ax.set_xlabel(f"relative pose error ({unit}, log scale)")
            ax.set_ylabel("share of pairs per bin (%)")
            ax.legend(fontsize=7)
    fig.suptitle(f"{RPE_BINS} log-spaced bins up to the largest error (nothing clipped); "
                 f"errors < {RPE_FLOOR:g} are counted in the legend", fontsize=8)
    fig.tight_layout()
    return fig


def rpe_distribution(rows: Sequence[SummaryRow], path: Path) -> Path:
    return _save(rpe_distribution_figure(rows), path)
