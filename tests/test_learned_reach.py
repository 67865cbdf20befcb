"""The learned detector reads each agent's sensor range within the evaluation range."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import roco_env
from roco_env.scenario import load_scenario
from roco_env.sensing import BevGrid, compute_visibility
from roco_env.sensing.learned import LearnedDetector
from roco_env.sensing.learned.model import covering_grid
from roco_env.traffic import make_traffic_source

GRID = BevGrid((-70.4, 70.4), (-40.0, 40.0), 0.8)
URBAN_RANGE = ((-140.8, 140.8), (-40.0, 40.0))  # the evaluation range of the urban scenes


@settings(max_examples=200, deadline=None)
@given(st.floats(-200.0, 0.0), st.floats(0.0, 200.0), st.floats(-100.0, 0.0),
       st.floats(0.0, 100.0))
def test_covering_grid_is_the_smallest_symmetric_growth_that_covers(x0, x1, y0, y1):
    grown = covering_grid(GRID, (x0, x1), (y0, y1))
    step = 2 * GRID.resolution
    assert grown.resolution == GRID.resolution
    assert grown.x_range[0] <= min(x0, -70.4) + 1e-6 and grown.x_range[1] >= max(x1, 70.4) - 1e-6
    assert grown.y_range[0] <= min(y0, -40.0) + 1e-6 and grown.y_range[1] >= max(y1, 40.0) - 1e-6
    assert grown.W % 4 == 0 and grown.H % 4 == 0
    for axis, trained, (low, high) in ((0, GRID.x_range, (x0, x1)), (1, GRID.y_range, (y0, y1))):
        edges = (grown.x_range, grown.y_range)[axis]
        grew = trained[0] - edges[0]
        assert grew == pytest.approx(edges[1] - trained[1])  # symmetric
        k = round(grew / step)
        assert grew == pytest.approx(k * step)  # whole feature cells
        if k:  # one feature cell less would not cover
            assert trained[0] - (k - 1) * step > low + 1e-6 or trained[1] + (k - 1) * step < (
                high - 1e-6)


@pytest.fixture(scope="module")
def roundabout_state():
    """4 CAVs (70 m LiDAR) and an RSU (100 m) with objects 72-100 m from it."""
    state = make_traffic_source(load_scenario("urban_roundabout")).reset(
        np.random.default_rng(1))
    return state, compute_visibility(state)


def test_raster_of_an_agent_covers_its_sensor_range_within_the_region():
    reach = LearnedDetector(region=URBAN_RANGE)
    assert LearnedDetector().raster_grid(100.0) == GRID  # no region: the trained grid
    assert reach.raster_grid(70.0) == GRID  # a 70 m CAV: the trained grid covers it
    rsu = reach.raster_grid(100.0)
    assert rsu.x_range == pytest.approx((-100.8, 100.8)) and rsu.y_range == GRID.y_range
    assert reach.raster_grid(250.0).x_range == pytest.approx(URBAN_RANGE[0])


@pytest.mark.parametrize("region", [((-10.0, 10.0),), ((5.0, -5.0), (-40.0, 40.0)),
                                    ((-10.0, float("nan")), (-40.0, 40.0)), "everywhere"])
def test_a_bad_region_is_a_clear_error(region):
    with pytest.raises(ValueError, match="learned detector region"):
        LearnedDetector(region=region)


def test_agents_with_a_longer_range_detect_farther_and_the_others_are_unchanged(
        roundabout_state):
    state, visibility = roundabout_state
    ranges = np.asarray(state.sensor_ranges)
    assert set(ranges.tolist()) == {70.0, 100.0}  # 4 CAVs at 70 m, the RSU at 100 m
    trained, reach = LearnedDetector(), LearnedDetector(region=URBAN_RANGE)
    before, maps_before = trained.perceive(state, visibility, np.random.default_rng(0))
    after, maps_after = reach.perceive(state, visibility, np.random.default_rng(0))
    rsu = int(np.flatnonzero(ranges == 100.0)[0])
    for agent in np.flatnonzero(ranges == 70.0):
        np.testing.assert_array_equal(after[agent].boxes, before[agent].boxes)
    far = np.abs(after[rsu].boxes[:, 0]) > 70.4
    assert far.any() and (after[rsu].object_ids[far] >= 0).any()  # true objects beyond 70.4 m
    assert not (np.abs(before[rsu].boxes[:, 0]) > 70.4 + 0.8).any()
    # All maps on the RSU's wider grid; a CAV's map is its trained-grid map, zero around it.
    assert maps_before.grid.W == 88 and maps_after.grid.W == 126
    cav = int(np.flatnonzero(ranges == 70.0)[0])
    padded = maps_after.maps[cav]
    torch.testing.assert_close(padded[:, :, 19:107], maps_before.maps[cav], rtol=0, atol=0)
    assert not padded[:, :, :19].any() and not padded[:, :, 107:].any()


def test_the_dataset_shaped_scene_detects_to_its_100_m_range():
    env = roco_env.parallel_env("dair_like", max_cycles=3, detector="learned")
    env.reset(seed=0)
    far = 0
    for _ in range(3):
        _, _, _, _, infos = env.step({a: np.zeros((1, 3)) for a in env.agents})
        for info in infos.values():
            boxes = np.asarray(info["fused_boxes"])[np.asarray(info["fused_mask"], dtype=bool)]
            far += int((np.abs(boxes[:, 0]) > 72.0).sum())
    assert far > 0
