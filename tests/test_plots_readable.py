"""Plots a researcher reads right: labelled axes, shared y across panels, x labels inside
the picture, every pose error on the histogram's axis (no tail folded into a last bin, no
spike flattening the rest), no log axis for a loss that goes negative."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg

from roco_env.sweeps.aggregate import SummaryRow


def _row(policy: str, noise: float, density: float | None, ap70: float,
         after: np.ndarray | None = None, before: np.ndarray | None = None) -> SummaryRow:
    before = np.zeros((0, 2)) if before is None else before
    return SummaryRow("crowded_intersection", density, noise, policy, 20, {}, 1, 0,
                      {"ap70": ap70}, before, before if after is None else after)


def _line_rows() -> list[SummaryRow]:
    return [_row(policy, noise, density, ap)
            for noise in (0.4, 0.8)
            for density, ap in ((4.0, 0.7), (9.0, 0.5), (15.0, 0.3))
            for policy in ("identity", "roco")]


def _visible_axes(fig):
    return [ax for ax in fig.axes if ax.get_visible()]


@pytest.mark.parametrize("name", ["ap_vs_density_figure", "ap_vs_noise_figure"])
def test_line_plots_share_y_and_keep_their_labels_inside_the_picture(name):
    from roco_env.sweeps import plots

    fig = getattr(plots, name)(_line_rows())
    axes = _visible_axes(fig)
    assert len(axes) >= 2
    assert all(axes[0].get_shared_y_axes().joined(axes[0], ax) for ax in axes[1:])
    renderer = FigureCanvasAgg(fig).get_renderer()
    fig.draw(renderer)
    picture = fig.bbox
    boxes = []
    for ax in axes:
        assert ax.get_xlabel() and ax.get_ylabel() == "AP@0.7 (%)"
        for label in (ax.xaxis.label, ax.yaxis.label):
            box = label.get_window_extent(renderer)
            assert picture.x0 <= box.x0 and box.x1 <= picture.x1, label.get_text()
            assert picture.y0 <= box.y0 and box.y1 <= picture.y1, label.get_text()
        boxes.append(ax.xaxis.label.get_window_extent(renderer))
    for i, first in enumerate(boxes):
        assert not any(first.overlaps(other) for other in boxes[i + 1:])


def test_rpe_histogram_spans_every_error_and_counts_the_exact_zeros():
    from roco_env.sweeps import plots

    rng = np.random.default_rng(0)
    before = np.abs(rng.normal(0.8, 0.3, (200, 2)))
    # CoAlign-like: 196 pairs corrected to ~5 cm, 4 failures (2%) at 40 m / 30 deg, far
    # past the uncorrected errors' 99th percentile
    failing = np.abs(rng.normal(0.05, 0.01, (200, 2)))
    failing[:4] = [40.0, 30.0]
    rows = [_row("identity", 0.8, None, 0.1, before, before),
            _row("coalign", 0.8, None, 0.4, failing, before),
            _row("oracle", 0.8, None, 0.7, np.zeros((200, 2)), before)]
    fig = plots.rpe_distribution_figure(rows)
    translation, rotation = fig.axes
    for ax, largest, unit in ((translation, 40.0, "m"), (rotation, 30.0, "deg")):
        assert ax.get_xscale() == "log" and ax.get_xlim()[1] >= largest
        assert ax.get_xlabel() == f"relative pose error ({unit}, log scale)"
        assert ax.get_ylabel() == "share of pairs per bin (%)"
        (coalign,) = [p for p in ax.patches if p.get_label() == "coalign"]
        heights = coalign.get_xy()
        # the failures are a bar of 2% in the last bin, at the largest error
        assert heights[:, 0].max() == pytest.approx(largest)
        assert heights[heights[:, 0] >= 0.99 * largest, 1].max() == pytest.approx(2.0)
        labels = [t.get_text() for t in ax.get_legend().get_texts()]
        assert f"oracle (100% < 0.001 {unit})" in labels  # not a spike flattening the rest
        (oracle,) = [p for p in ax.patches if p.get_label().startswith("oracle")]
        assert oracle.get_xy()[:, 1].max() == 0.0


def test_loss_curves_have_labelled_linear_axes_for_a_negative_loss():
    pytest.importorskip("torch")
    from roco_env.training.detector_report import loss_curves_figure

    steps = 90
    history = {name: list(np.linspace(0.5, 0.2, steps))
               for name in ("total", "fused", "heatmap", "offset", "size", "yaw")}
    history["nll"] = list(np.linspace(-1.8, -2.1, steps))
    history["single"] = list(np.linspace(-0.2, 0.1, steps))  # crosses zero, like the shipped run
    fig = loss_curves_figure(history)
    assert len(fig.axes) == 2
    for ax in fig.axes:
        assert ax.get_xlabel() == "training step" and ax.get_ylabel()
        negative = any(np.min(line.get_ydata()) < 0 for line in ax.get_lines())
        assert negative and ax.get_yscale() == "linear"
