"""Simulated LiDAR scans and rasters: determinism, sparsity, dropouts, spurious points, heights."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import run_python

from roco_env.scenario import load_scenario
from roco_env.sensing import BevGrid, compute_visibility
from roco_env.sensing.lidar import (
    LIDAR_CHANNELS,
    LidarScan,
    ScanNoise,
    ground_references,
    lidar_raster,
    lidar_rasters,
    sample_scans,
)
from roco_env.traffic import make_traffic_source

GRID = BevGrid((-70.4, 70.4), (-40.0, 40.0), 0.8)


@pytest.fixture(scope="module")
def scene():
    state = make_traffic_source(load_scenario("urban_intersection")).reset(
        np.random.default_rng(3))
    return state, compute_visibility(state)


def test_same_seed_same_scan_and_raster(scene):
    state, vis = scene
    a = sample_scans(state, vis, ScanNoise(), np.random.default_rng(7))
    b = sample_scans(state, vis, ScanNoise(), np.random.default_rng(7))
    c = sample_scans(state, vis, ScanNoise(), np.random.default_rng(8))
    for sa, sb in zip(a, b, strict=True):
        np.testing.assert_array_equal(lidar_raster(sa, vis.ray_ranges[0], GRID),
                                      lidar_raster(sb, vis.ray_ranges[0], GRID))
    assert not np.array_equal(a[0].x, c[0].x)  # sampled, not expected, returns


def test_raster_shape_and_channels(scene):
    state, vis = scene
    scan = sample_scans(state, vis, ScanNoise(), np.random.default_rng(0))[0]
    raster = lidar_raster(scan, vis.ray_ranges[0], GRID)
    assert raster.shape == (len(LIDAR_CHANNELS), GRID.H, GRID.W) and raster.dtype == np.float32
    occupied = raster[0] > 0
    assert occupied.any() and np.all(raster[1][~occupied] == 0.0)
    assert np.all(raster[1] >= raster[2] - 1e-6)  # max height >= mean height
    offsets = raster[[LIDAR_CHANNELS.index("mean_dx"), LIDAR_CHANNELS.index("mean_dy")]]
    assert np.all(np.abs(offsets) <= 0.5 + 1e-6) and np.all(offsets[:, ~occupied] == 0.0)
    assert np.abs(offsets[:, occupied]).mean() > 0.05  # points are spread inside their cells
    assert set(np.unique(raster[LIDAR_CHANNELS.index("observed")])) <= {0.0, 1.0}


def test_point_offsets_locate_points_inside_their_cell():
    """mean_dx / mean_dy: the mean position of a cell's points relative to its centre, in cells."""
    res = GRID.resolution
    x0, y0 = GRID.x_range[0] + 10 * res, GRID.y_range[0] + 20 * res  # corner of cell (20, 10)
    scan = LidarScan(x=np.array([x0 + 0.1 * res, x0 + 0.3 * res, x0 + 1.25 * res]),
                     y=np.array([y0 + 0.9 * res, y0 + 0.7 * res, y0 + 0.5 * res]),
                     z=np.ones(3), obj=np.zeros(3, dtype=np.int64))
    raster = lidar_raster(scan, np.zeros(720), GRID)
    dx, dy = raster[LIDAR_CHANNELS.index("mean_dx")], raster[LIDAR_CHANNELS.index("mean_dy")]
    assert (dx[20, 10], dy[20, 10]) == pytest.approx((0.2 - 0.5, 0.8 - 0.5), abs=1e-5)
    assert (dx[20, 11], dy[20, 11]) == pytest.approx((0.25 - 0.5, 0.0), abs=1e-5)
    assert np.count_nonzero(raster[0]) == 2


def test_points_thin_out_with_range(scene):
    """Range-dependent sparsity: points per visible object fall with its distance."""
    state, vis = scene
    scans = sample_scans(state, vis, ScanNoise(spurious_rate=0.0), np.random.default_rng(1))
    near, far = [], []
    for a, scan in enumerate(scans):
        counts = np.bincount(scan.obj, minlength=state.num_objects)
        seen = vis.visible[a] & (vis.fraction[a] > 0.5)
        near += counts[seen & (vis.distance[a] < 20.0)].tolist()
        far += counts[seen & (vis.distance[a] > 45.0)].tolist()
    assert near and far and np.mean(near) > 3.0 * np.mean(far)


def test_dropouts_and_spurious_returns(scene):
    state, vis = scene
    dark = sample_scans(state, vis, ScanNoise(dropout=1.0, spurious_rate=25.0),
                        np.random.default_rng(2))
    assert all(np.all(s.obj == -1) for s in dark)  # every true return dropped
    assert sum(s.x.size for s in dark) > 0  # spurious points remain
    for a, s in enumerate(dark):
        assert np.all(np.hypot(s.x, s.y) <= state.sensor_ranges[a] + 1e-9)
    clean = sample_scans(state, vis, ScanNoise(dropout=0.0, range_dropout=0.0,
                                               spurious_rate=0.0), np.random.default_rng(2))
    lossy = sample_scans(state, vis, ScanNoise(dropout=0.3, spurious_rate=0.0),
                         np.random.default_rng(2))
    assert sum(s.x.size for s in lossy) < 0.8 * sum(s.x.size for s in clean)


def test_heights_are_relative_to_the_agents_ground(scene):
    """Lifting the whole world (a hill) leaves every scan's heights unchanged."""
    state, vis = scene
    boxes = np.array(state.object_boxes)
    boxes[:, 2] += 12.0
    lifted = dataclasses.replace(state, object_boxes=boxes,
                                 ground_heights=np.asarray(state.ground_heights) + 12.0)
    np.testing.assert_allclose(ground_references(lifted), ground_references(state) + 12.0)
    # Visibility measures its heights from the ground under each agent, as the env does.
    lifted_vis = compute_visibility(lifted)
    np.testing.assert_allclose(lifted_vis.hits.top, vis.hits.top)
    for s0, s1 in zip(sample_scans(state, vis, ScanNoise(), np.random.default_rng(4)),
                      sample_scans(lifted, lifted_vis, ScanNoise(), np.random.default_rng(4)),
                      strict=True):
        np.testing.assert_allclose(s0.z, s1.z, atol=1e-9)


@pytest.mark.parametrize("field,value", [("dropout", -0.1), ("range_noise", float("nan")),
                                         ("spurious_rate", "many")])
def test_scan_noise_rejects_bad_values(field, value):
    with pytest.raises(ValueError, match=f"ScanNoise.{field}"):
        ScanNoise(**{field: value})


def test_batched_rasters_equal_each_scan_rastered_alone(scene):
    state, vis = scene
    scans = sample_scans(state, vis, ScanNoise(), np.random.default_rng(1))
    batch = lidar_rasters(scans, vis.ray_ranges, GRID)
    assert batch.shape == (len(scans), len(LIDAR_CHANNELS), GRID.H, GRID.W)
    for a, scan in enumerate(scans):
        np.testing.assert_array_equal(batch[a], lidar_raster(scan, vis.ray_ranges[a], GRID))


def test_the_lidar_module_does_not_import_torch():
    """Scans and rasters are the numpy core path: the learned detector alone needs torch."""
    probe = "import sys, roco_env.sensing.lidar; print('torch' in sys.modules)"
    assert run_python(probe) == "False"


def test_raster_equals_a_direct_numpy_binning(scene):
    """The compiled binning loop against unbuffered numpy accumulation: counts and maxima
    exactly, the float32 mean height to one float32 ulp (a float64 sum an ulp apart may
    round to either neighbour)."""
    state, vis = scene
    scan = sample_scans(state, vis, ScanNoise(), np.random.default_rng(5))[2]
    scan = dataclasses.replace(scan, z=scan.z - 1.0)  # some points below the reference
    raster = lidar_raster(scan, vis.ray_ranges[2], GRID)
    row, col = GRID.cell_index(scan.x, scan.y)
    inside = (row[row >= 0], col[row >= 0])
    count, total, top = (np.zeros((GRID.H, GRID.W)) for _ in range(3))
    np.add.at(count, inside, 1.0)
    np.add.at(total, inside, scan.z[row >= 0])
    np.maximum.at(top, inside, scan.z[row >= 0])  # top starts at 0: the max of z and 0
    assert (count > 1).sum() > 100 and (scan.z < 0).any()
    np.testing.assert_array_equal(raster[0], np.log1p(count).astype(np.float32))
    np.testing.assert_array_equal(raster[1], top.astype(np.float32))
    np.testing.assert_allclose(raster[2], (total / np.maximum(count, 1)).astype(np.float32),
                               rtol=float(np.finfo(np.float32).eps), atol=0)
    u = (scan.x[row >= 0] - GRID.x_range[0]) / GRID.resolution
    v = (scan.y[row >= 0] - GRID.y_range[0]) / GRID.resolution
    for channel, offset in (("mean_dx", u - inside[1] - 0.5), ("mean_dy", v - inside[0] - 0.5)):
        summed = np.zeros((GRID.H, GRID.W))
        np.add.at(summed, inside, offset)
        np.testing.assert_allclose(raster[LIDAR_CHANNELS.index(channel)],
                                   summed / np.maximum(count, 1), atol=1e-6)


@pytest.mark.parametrize("flip_x, flip_y", [(True, False), (False, True), (True, True)])
def test_a_mirrored_raster_is_the_raster_of_the_mirrored_scan(scene, flip_x, flip_y):
    """Training's mirror augmentation: flipping a raster must give what the sensor would
    record of the mirrored scene, point offsets included (the grid is symmetric)."""
    import torch

    from roco_env.training.train import mirror_rasters

    state, vis = scene
    scan = sample_scans(state, vis, ScanNoise(), np.random.default_rng(6))[0]
    # A point on a cell edge (x = 0, say) falls in the cell above the edge both ways.
    on_edge = np.zeros(scan.x.size, dtype=bool)
    for value, low in ((scan.x, GRID.x_range[0]), (scan.y, GRID.y_range[0])):
        cells = (value - low) / GRID.resolution
        on_edge |= np.abs(cells - np.round(cells)) < 1e-6
    scan = LidarScan(*(getattr(scan, k)[~on_edge] for k in ("x", "y", "z", "obj")))
    mirrored = dataclasses.replace(scan, x=-scan.x if flip_x else scan.x,
                                   y=-scan.y if flip_y else scan.y)
    no_rays = np.zeros(720)
    got = mirror_rasters(torch.from_numpy(lidar_rasters([scan], no_rays[None], GRID)),
                         flip_x, flip_y)[0].numpy()
    want = lidar_raster(mirrored, no_rays, GRID)
    np.testing.assert_allclose(got, want, atol=1e-5)


def test_ray_hits_come_sorted_by_agent(scene):
    """sample_scans takes each agent's returns as one slice of the hits."""
    _, vis = scene
    assert np.unique(vis.hits.agent).size > 1 and np.all(np.diff(vis.hits.agent) >= 0)
