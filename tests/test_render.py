"""The BEV picture: the chosen ego, a legend, a scale bar, the whole frame on the canvas,
a title naming what is shown, the evaluation range; GIFs written frame by frame."""

import gc
import weakref

import numpy as np
import pytest
from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar
from PIL import Image

import roco_env
from roco_env.render import bev_figure


@pytest.fixture
def env():
    env = roco_env.parallel_env(cavs=2, rsus=1, density=1.0, max_cycles=2,
                                render_mode="rgb_array", render_ego="rsu_0")
    env.reset(seed=0)
    env.step({a: np.zeros(env.action_space(a).shape) for a in env.agents})
    return env


def _figure(env):
    frame, fused = env._shown
    ego = env.possible_agents.index(env.render_ego)
    return bev_figure(frame, ego, fused.get(env.render_ego), agent_ids=env.possible_agents)


def test_the_chosen_ego_is_drawn_and_named(env):
    assert env.render_ego == "rsu_0"
    labels = [t.get_text() for t in _figure(env).axes[0].get_legend().get_texts()]
    assert "fused (rsu_0, true pose)" in labels
    env.render_ego = "cav_1"
    labels = [t.get_text() for t in _figure(env).axes[0].get_legend().get_texts()]
    assert "fused (cav_1, true pose)" in labels
    assert env.render().shape == (640, 640, 3)
    with pytest.raises(ValueError, match="unknown agent 'cav_9'"):
        env.render_ego = "cav_9"
    with pytest.raises(ValueError, match="unknown agent"):
        roco_env.parallel_env(cavs=2, rsus=0, render_ego="rsu_0")


def test_legend_names_every_agent_and_mark(env):
    labels = {t.get_text() for t in _figure(env).axes[0].get_legend().get_texts()}
    assert {"ground truth", "true pose", "reported pose", "cav_0 boxes", "cav_1 boxes",
            "rsu_0 boxes"} <= labels


def test_scale_bar_is_a_round_length(env):
    ax = _figure(env).axes[0]
    (bar,) = [a for a in ax.artists if isinstance(a, AnchoredSizeBar)]
    length = float(bar.txt_label.get_text().removesuffix(" m"))
    span = ax.get_xlim()[1] - ax.get_xlim()[0]
    assert length in (5, 10, 20, 50, 100, 200, 500, 1000) and length <= span / 5


def test_the_frame_border_is_inside_the_picture(env):
    image = env.render().astype(int)
    dark_rows = np.nonzero((image.sum(axis=2) < 200).mean(axis=1) > 0.9)[0]
    dark_cols = np.nonzero((image.sum(axis=2) < 200).mean(axis=0) > 0.8)[0]
    height, width = image.shape[:2]
    # the bottom border is a full dark row, with margin below it; likewise every side
    assert dark_rows.size and height - 16 < dark_rows.max() < height - 1
    assert 0 < dark_cols.min() and dark_cols.max() < width - 1


def test_the_title_names_policy_scenario_and_noise_and_the_evaluation_range_is_drawn(
        env, monkeypatch):
    import roco_env.render as rendering

    figures = []

    def keep(*args, **kwargs):
        figures.append(bev_figure(*args, **kwargs))
        return figures[-1]

    monkeypatch.setattr(rendering, "bev_figure", keep)
    env.render_caption = "policy roco"
    env.render()
    (fig,) = figures
    title = fig.get_suptitle()
    cfg = env.config
    assert title.splitlines() == [
        f"policy roco  {cfg.name}",
        f"step 1  ego rsu_0  noise gaussian {cfg.noise.sigma_t:g} m / {cfg.noise.sigma_r:g} deg"]
    ax = fig.axes[0]
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert "evaluation range (rsu_0: x -140.8..140.8 m, y -40..40 m)" in labels
    # the dotted rectangle: the ego-frame range corners placed with the ego's true pose
    ego_pose = env._shown[0].state.agent_poses[env.possible_agents.index("rsu_0")]
    c, s = np.cos(ego_pose[2]), np.sin(ego_pose[2])
    corners = np.array([[-140.8, -40.0], [140.8, -40.0], [140.8, 40.0], [-140.8, 40.0]])
    expected = corners @ np.array([[c, s], [-s, c]]) + ego_pose[:2]
    def same_corners(path) -> bool:
        return len(path.vertices) >= 4 and np.allclose(
            np.sort(path.vertices[:4], axis=0), np.sort(expected, axis=0))

    assert sum(same_corners(path) for coll in ax.collections for path in coll.get_paths()) == 1


def test_gif_stream_round_trips_every_frame(tmp_path):
    from roco_env.render import GifStream

    rng = np.random.default_rng(0)
    frames = [Image.fromarray(rng.integers(0, 256, (30, 40, 3), dtype=np.uint8))
              for _ in range(3)]
    path = tmp_path / "sub" / "x.gif"
    with GifStream(path, fps=4) as gif:
        for frame in frames:
            gif.append(frame)
    assert gif.frames == 3
    with Image.open(path) as image:
        assert image.n_frames == 3 and image.info["loop"] == 0
        for k, frame in enumerate(frames):
            image.seek(k)
            assert image.info["duration"] == 250
            # exactly the frame on its own adaptive palette (GIF is 256 colours)
            quantised = frame.convert("P", palette=Image.Palette.ADAPTIVE).convert("RGB")
            assert np.array_equal(np.asarray(image.convert("RGB")), np.asarray(quantised))
    with pytest.raises(ValueError, match="no frame was appended"), GifStream(path, fps=4):
        pass
    assert not path.exists()
    with pytest.raises(ValueError, match="fps must be > 0"):
        GifStream(path, fps=0)


def test_render_cli_streams_frames_instead_of_holding_them(tmp_path, monkeypatch):
    """Every drawn frame is written and dropped: at most one is alive when the next is drawn
    (the old CLI kept a list of all of them until the GIF was saved)."""
    import roco_env.cli.render_command as render_cli
    from roco_env.cli import main

    live, most = set(), [0]
    draw = render_cli._frame

    def counted(env):
        gc.collect()
        most[0] = max(most[0], len(live))
        frame = draw(env)
        live.add(id(frame))
        weakref.finalize(frame, live.discard, id(frame))
        return frame

    monkeypatch.setattr(render_cli, "_frame", counted)
    gif = tmp_path / "episode.gif"
    assert main(["render", "--policy", "identity", "--steps", "5", "--gif", str(gif),
                 "--out", str(tmp_path / "png"), "--set", "cavs=2", "--set", "rsus=1"]) == 0
    assert most[0] <= 1
    pngs = sorted((tmp_path / "png").glob("frame_*.png"))
    assert len(pngs) == 5
    with Image.open(gif) as image:
        assert image.n_frames == 5
        image.seek(4)
        with Image.open(pngs[4]) as last:
            quantised = last.convert("P", palette=Image.Palette.ADAPTIVE).convert("RGB")
        assert np.array_equal(np.asarray(image.convert("RGB")), np.asarray(quantised))
