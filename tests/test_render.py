"""The BEV picture: the chosen ego, a legend, a scale bar, the whole frame on the canvas."""

import numpy as np
import pytest
from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

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
