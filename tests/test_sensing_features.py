"""BEV features: the right cells light up, warp_bev moves them by the known transform."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import car, make_state
from hypothesis import given, settings
from hypothesis import strategies as st

from roco_env.geometry import se2_apply, se2_inverse
from roco_env.sensing import CHANNELS, BevGrid, bev_features, compute_visibility, warp_bev

GRID = BevGrid((-40.0, 40.0), (-20.0, 20.0), 0.4)


def single_car_features(grid: BevGrid = GRID, x: float = 20.0) -> torch.Tensor:
    """A car at (x, 0) ahead of a CAV at the origin (agent frame = world frame)."""
    state = make_state([car(x, 0.0)], [[0.0, 0.0, 0.0]], ranges=[35.0])
    return bev_features(compute_visibility(state), 0, grid)


def lit_cells(features: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Cell-centre coordinates (x, y) of cells with returns."""
    rows, cols = np.nonzero(features[0].numpy() > 0.05)
    return (GRID.x_range[0] + (cols + 0.5) * GRID.resolution,
            GRID.y_range[0] + (rows + 0.5) * GRID.resolution)


def test_grid_shape_and_axis_convention():
    assert (GRID.H, GRID.W) == (100, 200)
    row, col = GRID.cell_index(np.array([-39.9, 39.9, 0.1, 50.0]), np.array([-19.9, 0.1, 19.9, 0]))
    np.testing.assert_array_equal(row, [0, 50, 99, -1])
    np.testing.assert_array_equal(col, [0, 199, 100, -1])


def test_single_car_lights_its_near_face():
    feats = single_car_features()
    assert feats.dtype == torch.float32 and feats.shape == (len(CHANNELS), GRID.H, GRID.W)
    x, y = lit_cells(feats)
    face = 20.0 - 4.5 / 2  # the LiDAR hits the rear bumper at x = 17.75
    assert len(x) >= 4
    assert np.all(np.abs(x - face) <= GRID.resolution)
    assert np.all(np.abs(y) <= 1.9 / 2 + GRID.resolution)
    row, col = GRID.cell_index(np.array([face + 0.01]), np.array([0.01]))
    assert feats[0, row[0], col[0]] > 0
    assert feats[1, row[0], col[0]] == pytest.approx(1.5)  # max height = roof
    assert feats[1].max() == pytest.approx(1.5) and feats[0].sum() > 0


def test_observed_channel_is_free_space_before_the_first_hit_and_in_range():
    feats = single_car_features()
    def observed(x, y):
        row, col = GRID.cell_index(np.array([x]), np.array([y]))
        return float(feats[2, row[0], col[0]])
    assert observed(10.0, 0.2) == 1.0        # in front of the car
    assert observed(-10.0, 10.0) == 1.0      # open space elsewhere
    assert observed(25.0, 0.2) == 0.0        # shadow behind the car
    assert observed(-36.0, -0.5) == 0.0      # beyond the 35 m range


@pytest.mark.parametrize("shift", [(4.0, 0.0), (-6.0, 2.8), (0.0, -3.2)])
def test_warp_by_known_translation_moves_cells(shift):
    feats = single_car_features()
    warped = warp_bev(feats, np.array([shift[0], shift[1], 0.0]), GRID)
    x0, y0 = lit_cells(feats)
    x1, y1 = lit_cells(warped)
    assert abs(x1.mean() - (x0.mean() + shift[0])) <= GRID.resolution
    assert abs(y1.mean() - (y0.mean() + shift[1])) <= GRID.resolution
    assert float(warped[0].sum()) == pytest.approx(float(feats[0].sum()), rel=0.05)


def test_warp_by_rotation_and_batch():
    feats = single_car_features()
    pose = np.array([[0.0, 0.0, np.pi / 2], [0.0, 0.0, 0.0]])
    warped = warp_bev(torch.stack([feats, feats]), pose, GRID)
    x, y = lit_cells(warped[0])
    # The face at x = 17.75 ahead is now at y = 17.75 to the left.
    assert abs(y.mean() - 17.75) <= GRID.resolution and abs(x.mean()) <= GRID.resolution
    # Identity: cell centres map onto themselves (align_corners=False), up to float32.
    torch.testing.assert_close(warped[1], feats, atol=1e-4, rtol=0)


def test_warp_round_trip_restores_interior():
    feats = single_car_features()
    pose = np.array([3.0, -1.0, 0.3])
    back = warp_bev(warp_bev(feats, pose, GRID), se2_inverse(pose), GRID)
    x0, y0 = lit_cells(feats)
    x1, y1 = lit_cells(back)
    assert abs(x1.mean() - x0.mean()) <= GRID.resolution
    assert abs(y1.mean() - y0.mean()) <= GRID.resolution


@pytest.mark.parametrize("kwargs, name", [
    ({"x_range": (-10, 10), "y_range": (-10, 10), "resolution": 0.0}, "resolution"),
    ({"x_range": (10, -10), "y_range": (-10, 10)}, "x_range"),
    ({"x_range": (-10, 10), "y_range": (0, 0)}, "y_range"),
])
def test_bad_grid_rejected(kwargs, name):
    with pytest.raises(ValueError, match=name):
        BevGrid(**kwargs)


def test_bad_warp_and_agent_inputs_rejected():
    feats = single_car_features()
    with pytest.raises(ValueError, match="features"):
        warp_bev(feats[:, :10], np.zeros(3), GRID)
    with pytest.raises(ValueError, match="T_src_to_dst"):
        warp_bev(feats, np.zeros(2), GRID)
    vis = compute_visibility(make_state([car(20, 0)], [[0, 0, 0]]))
    with pytest.raises(ValueError, match="agent_index"):
        bev_features(vis, 3, GRID)


def _weighted_centroid(features: torch.Tensor) -> np.ndarray:
    weights = features[0].numpy().astype(float)
    rows, cols = np.indices(weights.shape)
    x = GRID.x_range[0] + (cols + 0.5) * GRID.resolution
    y = GRID.y_range[0] + (rows + 0.5) * GRID.resolution
    return np.array([(weights * x).sum(), (weights * y).sum()]) / weights.sum()


@settings(max_examples=15, deadline=None)
@given(dx=st.floats(-8, 8), dy=st.floats(-5, 5), yaw=st.floats(-np.pi, np.pi))
def test_warp_moves_the_return_centroid_by_the_pose(dx, dy, yaw):
    feats = single_car_features(x=12.0)
    pose = np.array([dx, dy, yaw])
    moved = _weighted_centroid(warp_bev(feats, pose, GRID))
    expected = se2_apply(pose, _weighted_centroid(feats))
    assert np.hypot(*(moved - expected)) <= GRID.resolution
