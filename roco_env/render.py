"""BEV pictures of a frame (DESIGN.md section 9) with matplotlib's Agg canvas.

World frame, x to the right, y up, metres. Drawn: ground truth (grey
footprints), every agent's detections placed with its REPORTED pose (so pose
errors show as misplaced boxes, one colour per agent), the ego's fused boxes
(black, dashed) placed with its true pose, each agent's true pose (filled
triangle pointing along its heading) and reported pose (hollow triangle).
"""

from __future__ import annotations

import numpy as np
from gymnasium import logger
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import PolyCollection
from matplotlib.figure import Figure

from roco_env.fusion import FusedDetections
from roco_env.geometry import box_corners_bev, transform_boxes
from roco_env.pipeline import PerceptionFrame

_MARGIN_M = 30.0
_MIN_SPAN_M = 80.0


def render_bev(frame: PerceptionFrame, ego: int, fused: FusedDetections | None, title: str = "",
               size_px: int = 640) -> np.ndarray:
    """RGB image (size_px, size_px, 3) uint8 of ``frame`` seen from above.

    ego: index of the agent whose fused detections ``fused`` (ego true frame) are drawn.
    """
    fig = Figure(figsize=(size_px / 100, size_px / 100), dpi=100)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_axes((0.0, 0.0, 1.0, 0.94))
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
    fig.suptitle(title, fontsize=9, y=0.99)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


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
