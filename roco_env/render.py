"""BEV pictures of a frame with matplotlib's Agg canvas.

World frame, x to the right, y up, metres. Drawn: ground truth (grey
footprints), every agent's detections placed with its REPORTED pose (so pose
errors show as misplaced boxes, one colour per agent), the ego's fused boxes
(black, dashed) placed with its true pose, each agent's true pose (filled
triangle pointing along its heading) and reported pose (hollow triangle); a
legend names the colours and a scale bar gives the metres. The env chooses the
ego with ``render_ego`` (constructor argument or attribute).
"""

from __future__ import annotations

import numpy as np
from gymnasium import logger
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import PolyCollection
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

from roco_env.fusion import FusedDetections
from roco_env.geometry import box_corners_bev, transform_boxes
from roco_env.pipeline import PerceptionFrame

_MARGIN_M = 30.0
_MIN_SPAN_M = 80.0
# Scale-bar lengths (m) to choose from: the longest at most a fifth of the view.
_SCALE_STEPS_M = (5.0, 10.0, 20.0, 50.0, 100.0, 200.0, 500.0, 1000.0)
# The axes sit inside the figure with a margin, so no border line falls off the canvas.
_AXES_RECT = (0.01, 0.01, 0.98, 0.92)


def render_bev(frame: PerceptionFrame, ego: int, fused: FusedDetections | None, title: str = "",
               size_px: int = 640, agent_ids: list[str] | None = None) -> np.ndarray:
    """RGB image (size_px, size_px, 3) uint8 of ``frame`` seen from above (see :func:`bev_figure`)."""
    fig = bev_figure(frame, ego, fused, title, size_px, agent_ids)
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def bev_figure(frame: PerceptionFrame, ego: int, fused: FusedDetections | None, title: str = "",
               size_px: int = 640, agent_ids: list[str] | None = None) -> Figure:
    """The matplotlib figure of ``frame`` seen from above (``size_px`` square at 100 dpi).

    ego: index of the agent whose fused detections ``fused`` (ego true frame) are
    drawn; agent_ids: names for the legend (default ``frame.state.agent_ids``).
    """
    fig = Figure(figsize=(size_px / 100, size_px / 100), dpi=100)
    ax = fig.add_axes(_AXES_RECT)
    state = frame.state
    true_poses = np.asarray(state.agent_poses, dtype=float)
    ax.add_collection(PolyCollection(box_corners_bev(state.object_boxes), facecolors="0.85",
                                     edgecolors="0.45", linewidths=0.6, zorder=1))
    colours = [f"C{a % 10}" for a in range(state.num_agents)]
    for a, detections in enumerate(frame.detections):
        placed = transform_boxes(detections.boxes, frame.reported_poses[a])
        ax.add_collection(PolyCollection(box_corners_bev(placed), facecolors="none",
                                         edgecolors=colours[a], linewidths=0.9, zorder=2))
    if fused is not None and len(fused):
        placed = transform_boxes(fused.boxes, true_poses[ego])
        ax.add_collection(PolyCollection(box_corners_bev(placed), facecolors="none",
                                         edgecolors="black", linewidths=1.1, linestyles="--",
                                         zorder=3))
    for a in range(state.num_agents):
        _pose_marker(ax, true_poses[a], colours[a], filled=True)
        _pose_marker(ax, frame.reported_poses[a], colours[a], filled=False)
    centre = true_poses[:, :2].mean(axis=0) if state.num_agents else np.zeros(2)
    half = max(_MIN_SPAN_M / 2, float(np.abs(true_poses[:, :2] - centre).max(initial=0.0))
               + _MARGIN_M)
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    _legend(ax, list(agent_ids or state.agent_ids), colours, ego)
    ax.add_artist(_scale_bar(ax, 2 * half))
    fig.suptitle(title, fontsize=9, y=0.99)
    return fig


def _legend(ax, names: list[str], colours: list[str], ego: int) -> None:
    """What each colour and line style means; the ego is named."""
    handles = [
        Patch(facecolor="0.85", edgecolor="0.45", label="ground truth"),
        Line2D([], [], color="black", linestyle="--", label=f"fused ({names[ego]}, true pose)"),
        Line2D([], [], color="0.3", marker="^", linestyle="none", label="true pose"),
        Line2D([], [], color="0.3", marker="^", markerfacecolor="none", linestyle="none",
               label="reported pose"),
    ]
    handles += [Patch(facecolor="none", edgecolor=colour, label=f"{name} boxes")
                for name, colour in zip(names, colours, strict=True)]
    ax.legend(handles=handles, loc="upper left", fontsize=6.5, framealpha=0.85,
              ncols=2 if len(handles) > 8 else 1)


def _scale_bar(ax, span_m: float) -> AnchoredSizeBar:
    """A bar of a round number of metres, at most a fifth of the view's width."""
    length = max([step for step in _SCALE_STEPS_M if step <= span_m / 5], default=1.0)
    return AnchoredSizeBar(ax.transData, length, f"{length:g} m", "lower right", pad=0.5,
                           borderpad=0.6, sep=3, frameon=True, size_vertical=span_m / 250,
                           fontproperties={"size": 7})


def _pose_marker(ax, pose: np.ndarray, colour: str, filled: bool) -> None:
    """A triangle 4 m long at ``pose`` pointing along its yaw."""
    outline = np.array([[2.5, 0.0], [-1.5, 1.3], [-1.5, -1.3]])
    c, s = np.cos(pose[2]), np.sin(pose[2])
    points = outline @ np.array([[c, s], [-s, c]]) + pose[:2]
    ax.add_collection(PolyCollection([points], facecolors=colour if filled else "none",
                                     edgecolors=colour, linewidths=1.2, zorder=4))


class HumanViewer:
    """Shows frames in a matplotlib window; without an interactive backend, warns once.

    Never raises on a headless machine: the env's ``human`` mode then behaves as
    a no-op (use ``render_mode="rgb_array"`` to get the pictures).
    """

    _NON_INTERACTIVE = {"agg", "pdf", "ps", "svg", "pgf", "cairo", "template"}

    def __init__(self, fps: int) -> None:
        import matplotlib

        self.pause = 1.0 / max(fps, 1)
        self.interactive = matplotlib.get_backend().lower() not in self._NON_INTERACTIVE
        self._figure = None
        self._image = None
        if not self.interactive:
            logger.warn(f"render_mode='human' needs an interactive matplotlib backend; "
                        f"the current one is {matplotlib.get_backend()!r} (no display), so "
                        "frames are not shown. Use render_mode='rgb_array' to get them.")

    def show(self, image: np.ndarray) -> None:
        if not self.interactive:
            return
        import matplotlib.pyplot as plt

        if self._figure is None or not plt.fignum_exists(self._figure.number):
            self._figure = plt.figure("roco-env")
            self._image = self._figure.add_subplot().imshow(image)
            self._image.axes.set_axis_off()
        else:
            self._image.set_data(image)
        plt.pause(self.pause)

    def close(self) -> None:
        if self._figure is not None:
            import matplotlib.pyplot as plt

            plt.close(self._figure)
            self._figure = None
