"""BEV pictures of a frame with matplotlib's Agg canvas.

World frame, x to the right, y up, metres. Drawn: ground truth (grey
footprints), every agent's detections placed with its REPORTED pose (so pose
errors show as misplaced boxes, one colour per agent), the ego's fused boxes
(black, dashed) placed with its true pose, each agent's true pose (filled
triangle pointing along its heading) and reported pose (hollow triangle); a
legend names the colours and a scale bar gives the metres; the ego's evaluation
range (what its AP scores) is a dotted rectangle. The env chooses the ego with
``render_ego`` (constructor argument or attribute). :class:`GifStream` writes
frames to an animated GIF one at a time.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from types import TracebackType

import numpy as np
from gymnasium import logger
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import PolyCollection
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar
from PIL import GifImagePlugin, Image

from roco_env.fusion import FusedDetections
from roco_env.geometry import box_corners_bev, transform_boxes
from roco_env.pipeline import PerceptionFrame
from roco_env.scenario import NoiseConfig

_MARGIN_M = 30.0
_MIN_SPAN_M = 80.0
# Scale-bar lengths (m) to choose from: the longest at most a fifth of the view.
_SCALE_STEPS_M = (5.0, 10.0, 20.0, 50.0, 100.0, 200.0, 500.0, 1000.0)
# The axes sit inside the figure with a margin, so no border line falls off the canvas.
_AXES_RECT = (0.01, 0.01, 0.98, 0.92)


EvaluationRange = tuple[Sequence[float], Sequence[float]]


def render_bev(frame: PerceptionFrame, ego: int, fused: FusedDetections | None, title: str = "",
               size_px: int = 640, agent_ids: list[str] | None = None,
               evaluation_range: EvaluationRange | None = None) -> np.ndarray:
    """RGB image (size_px, size_px, 3) uint8 of ``frame`` seen from above (see :func:`bev_figure`)."""
    fig = bev_figure(frame, ego, fused, title, size_px, agent_ids, evaluation_range)
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def bev_figure(frame: PerceptionFrame, ego: int, fused: FusedDetections | None, title: str = "",
               size_px: int = 640, agent_ids: list[str] | None = None,
               evaluation_range: EvaluationRange | None = None) -> Figure:
    """The matplotlib figure of ``frame`` seen from above (``size_px`` square at 100 dpi).

    ego: index of the agent whose fused detections ``fused`` (ego true frame) are
    drawn; agent_ids: names for the legend (default ``frame.state.agent_ids``);
    evaluation_range: the ego-frame (x_range, y_range) in m its AP scores, drawn as
    a dotted rectangle around the ego's true pose (the view keeps its zoom on the
    agents, so long sides may run off the picture; the legend gives the extent).
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
    if evaluation_range is not None:
        _evaluation_rectangle(ax, true_poses[ego], evaluation_range)
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
    _legend(ax, list(agent_ids or state.agent_ids), colours, ego, evaluation_range)
    ax.add_artist(_scale_bar(ax, 2 * half))
    fig.suptitle(title, fontsize=9, y=0.995, va="top")
    return fig


def picture_title(scenario: str, step: int, ego: str, noise: NoiseConfig,
                  caption: str = "") -> str:
    """The picture's title: ``caption`` (e.g. the policy) and the scenario on the first
    line, then the step, the ego and the pose noise (model and levels, m / deg)."""
    levels = f"noise {noise.model} {noise.sigma_t:g} m / {noise.sigma_r:g} deg"
    if noise.per_agent:
        levels += " (some agents their own)"
    first = f"{caption}  {scenario}" if caption else scenario
    return f"{first}\nstep {step}  ego {ego}  {levels}"


def _evaluation_rectangle(ax, ego_pose: np.ndarray, evaluation_range: EvaluationRange) -> None:
    """The ego-frame rectangle x_range x y_range (m) placed with the ego's true pose."""
    (x0, x1), (y0, y1) = evaluation_range
    area = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0, x1 - x0, y1 - y0, 0.0, 0.0])
    placed = box_corners_bev(transform_boxes(area, ego_pose))
    ax.add_collection(PolyCollection(placed, facecolors="none", edgecolors="0.2",
                                     linewidths=1.2, linestyles=":", zorder=3))


def _legend(ax, names: list[str], colours: list[str], ego: int,
            evaluation_range: EvaluationRange | None) -> None:
    """What each colour and line style means; the ego is named."""
    handles = [
        Patch(facecolor="0.85", edgecolor="0.45", label="ground truth"),
        Line2D([], [], color="black", linestyle="--", label=f"fused ({names[ego]}, true pose)"),
        Line2D([], [], color="0.3", marker="^", linestyle="none", label="true pose"),
        Line2D([], [], color="0.3", marker="^", markerfacecolor="none", linestyle="none",
               label="reported pose"),
    ]
    if evaluation_range is not None:
        (x0, x1), (y0, y1) = evaluation_range
        handles.append(Line2D([], [], color="0.2", linestyle=":",
                              label=f"evaluation range ({names[ego]}: x {x0:g}..{x1:g} m, "
                              f"y {y0:g}..{y1:g} m)"))
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


class GifStream:
    """An animated GIF written one frame at a time (a context manager; ``append`` each frame).

    Memory stays one frame however long the episode: Pillow's own
    ``save(save_all=True, append_images=...)`` keeps every frame (palette-converted)
    in a list until the end, so the frames go through its GIF encoder one by one
    (``GifImagePlugin.getheader`` / ``getdata``). Each frame is quantised to its own
    adaptive 256-colour palette (a local colour table), shown ``1000 / fps`` ms
    (rounded), and the GIF loops forever.
    """

    def __init__(self, path: str | Path, fps: float) -> None:
        if not fps > 0:
            raise ValueError(f"fps must be > 0; got {fps}")
        self.path = Path(path)
        self.duration_ms = round(1000 / fps)
        self.frames = 0
        self._file = None

    def __enter__(self) -> GifStream:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = self.path.open("wb")
        return self

    def append(self, frame: Image.Image) -> None:
        """Encode and write ``frame`` (RGB); nothing of it is kept."""
        if self._file is None:
            raise ValueError("GifStream.append called outside its with-block")
        paletted = frame.convert("RGB").convert("P", palette=Image.Palette.ADAPTIVE)
        if self.frames == 0:
            header, _ = GifImagePlugin.getheader(paletted, info={"loop": 0})
            self._file.writelines(header)
        self._file.writelines(GifImagePlugin.getdata(paletted, duration=self.duration_ms,
                                                     include_color_table=True))
        self.frames += 1

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 traceback: TracebackType | None) -> None:
        self._file.write(b";")  # the GIF trailer
        self._file.close()
        self._file = None
        if self.frames == 0:
            self.path.unlink()
            if error is None:
                raise ValueError(f"no frame was appended to {self.path}; nothing written")


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
