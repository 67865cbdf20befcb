"""Visibility: range, ray-cast occlusion, RSU height, returns (hand-built scenes)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import CAR_SIZE, bus, car, make_state
from hypothesis import given, settings
from hypothesis import strategies as st
from shapely.geometry import LineString, Polygon

from roco_env.geometry import box_corners_bev
from roco_env.sensing import LidarModel, compute_visibility


def test_car_behind_bus_hidden_and_car_beside_visible():
    # Bus across the line of sight at x=15 (spanning y in [-6, 6]).
    state = make_state([car(35, 0), bus(15, 0, np.pi / 2), car(35, 20)], [[0, 0, 0]])
    vis = compute_visibility(state)
    assert vis.fraction[0, 0] == 0.0 and vis.returns[0, 0] == 0.0 and not vis.visible[0, 0]
    assert vis.fraction[0, 2] == pytest.approx(1.0) and vis.visible[0, 2]
    assert vis.visible[0, 1]


def test_half_occluded_car_has_half_visible_fraction():
    # The bus covers exactly the left half (y > 0) of the target's angular span.
    state = make_state([car(30, 0, np.pi / 2), bus(15, 6, np.pi / 2)], [[0, 0, 0]])
    vis = compute_visibility(state, azimuth_resolution_deg=0.05)
    assert vis.fraction[0, 0] == pytest.approx(0.5, abs=0.03)


def test_range_edge_and_returns_fall_with_distance():
    xs = [10.0, 30.0, 60.0, 69.0, 71.0]
    state = make_state([car(x, 5.0 * i) for i, x in enumerate(xs)], [[0, 0, 0]], ranges=[70.0])
    vis = compute_visibility(state)
    dist = np.hypot(xs, 5.0 * np.arange(5))
    assert list(vis.visible[0]) == list(dist <= 70.0)
    assert vis.returns[0, -1] == 0.0 and vis.fraction[0, -1] == 0.0
    in_range = vis.returns[0, dist <= 70.0]
    assert np.all(np.diff(in_range) < 0) and in_range[-1] > 0


def test_agent_never_sees_itself_and_agent_rotation_does_not_change_visibility():
    boxes = [car(0, 0), car(20, 3), car(-15, -4)]
    state = make_state(boxes, [[0, 0, 0], [0, 0, 2.0]], own_ids=[0, 0])
    vis = compute_visibility(state)
    assert not vis.visible[:, 0].any() and vis.fraction[0, 0] == 0.0
    np.testing.assert_allclose(vis.fraction[0], vis.fraction[1], atol=0.02)


@pytest.mark.parametrize("factor, expect_visible", [(1.0, True), (0.0, False)])
def test_rsu_height_factor_sees_over_cars(factor, expect_visible):
    # Same spot, a CAV (1.9 m) and an RSU (5.5 m mast) looking at a car behind a car.
    state = make_state([car(30, 0), car(15, 0)], [[0, 0, 0], [0, 0, 0]], kinds=("cav", "rsu"))
    vis = compute_visibility(state, rsu_height_factor=factor)
    assert vis.visible[1, 0] == expect_visible
    if expect_visible:
        assert vis.fraction[1, 0] > 0.9 > vis.fraction[0, 0]
        assert vis.returns[1, 0] > vis.returns[0, 0]
    else:
        assert vis.fraction[1, 0] == 0.0
    # The CAV's own view does not depend on the RSU factor.
    assert vis.fraction[0, 0] == compute_visibility(state).fraction[0, 0]


def _oracle_fraction_2d(boxes: np.ndarray, n_rays: int, reach: float) -> np.ndarray:
    """Shapely ray casting: rays hitting each footprint first / rays crossing it."""
    polys = [Polygon(c) for c in box_corners_bev(boxes)]
    first = np.zeros(len(polys))
    crossing = np.zeros(len(polys))
    for k in range(n_rays):
        angle = 2 * np.pi * k / n_rays
        ray = LineString([(0, 0), (reach * np.cos(angle), reach * np.sin(angle))])
        dists = {}
        for i, poly in enumerate(polys):
            inter = ray.intersection(poly)
            if not inter.is_empty:
                crossing[i] += 1
                dists[i] = min(np.hypot(*pt) for pt in np.asarray(inter.coords))
        if dists:
            first[min(dists, key=dists.get)] += 1
    return np.divide(first, crossing, out=np.zeros_like(first), where=crossing > 0)


def test_ground_level_rsu_matches_2d_shapely_ray_casting_oracle():
    rng = np.random.default_rng(3)
    xy = rng.uniform(-30, 30, size=(40, 2))
    xy = xy[np.hypot(*xy.T) > 6.0]
    keep = [0]
    for i in range(1, len(xy)):  # no overlapping footprints
        if np.min(np.hypot(*(xy[keep] - xy[i]).T)) > 5.5:
            keep.append(i)
    boxes = np.array([car(x, y, yaw) for (x, y), yaw in
                      zip(xy[keep], rng.uniform(-np.pi, np.pi, len(keep)), strict=True)])
    state = make_state(boxes, [[0, 0, 0]], kinds=("rsu",), ranges=[60.0])
    vis = compute_visibility(state, azimuth_resolution_deg=0.5, rsu_height_factor=0.0)
    oracle = _oracle_fraction_2d(boxes, n_rays=720, reach=60.0)
    np.testing.assert_allclose(vis.fraction[0], oracle, atol=1e-9)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(2, 12))
def test_removing_an_occluder_never_reduces_visibility(seed, n):
    rng = np.random.default_rng(seed)
    xs, ys, yaws = rng.uniform(8, 50, n), rng.uniform(-20, 20, n), rng.uniform(-np.pi, np.pi, n)
    boxes = np.array([car(x, y, yaw) for x, y, yaw in zip(xs, ys, yaws, strict=True)])
    full = compute_visibility(make_state(boxes, [[0, 0, 0]]), azimuth_resolution_deg=0.5)
    reduced = compute_visibility(make_state(boxes[1:], [[0, 0, 0]]), azimuth_resolution_deg=0.5)
    assert np.all((full.fraction >= 0) & (full.fraction <= 1))
    assert np.all(reduced.fraction[0] >= full.fraction[0, 1:] - 1e-12)
    assert np.all(reduced.returns[0] >= full.returns[0, 1:] - 1e-9)


def test_ray_ranges_stop_at_first_hit():
    state = make_state([car(20, 0)], [[0, 0, 0]], ranges=[50.0])
    vis = compute_visibility(state, azimuth_resolution_deg=1.0)
    assert vis.ray_ranges[0, 0] == pytest.approx(20 - CAR_SIZE[0] / 2)
    assert vis.ray_ranges[0, 90] == pytest.approx(50.0)


@pytest.mark.parametrize("ranges", [[0.0], [-5.0], [np.nan]])
def test_bad_sensor_range_rejected(ranges):
    with pytest.raises(ValueError, match="sensor_ranges"):
        compute_visibility(make_state([car(10, 0)], [[0, 0, 0]], ranges=ranges))


@pytest.mark.parametrize("kwargs, name", [
    ({"azimuth_resolution_deg": 0.0}, "azimuth_resolution_deg"),
    ({"rsu_height_factor": -1.0}, "rsu_height_factor"),
    ({"min_fraction": 1.5}, "min_fraction"),
])
def test_bad_arguments_rejected(kwargs, name):
    with pytest.raises(ValueError, match=name):
        compute_visibility(make_state([car(10, 0)], [[0, 0, 0]]), **kwargs)


def test_empty_scene():
    vis = compute_visibility(make_state(np.zeros((0, 7)), [[0, 0, 0]]))
    assert vis.fraction.shape == (1, 0) and vis.hits.x.size == 0


@pytest.mark.parametrize("kwargs, name", [
    ({"channels": 1}, "channels"),
    ({"fov_up_deg": -30.0}, "fov"),
    ({"horizontal_resolution_deg": 0.0}, "horizontal_resolution_deg"),
])
def test_bad_lidar_model_rejected(kwargs, name):
    with pytest.raises(ValueError, match=name):
        LidarModel(**kwargs)


def test_more_beams_give_proportionally_more_returns():
    state = make_state([car(25, 3)], [[0, 0, 0]])
    base = compute_visibility(state).returns[0, 0]
    dense = LidarModel(channels=127)  # half the beam spacing over the same field of view
    assert compute_visibility(state, lidar=dense).returns[0, 0] == pytest.approx(2 * base)
