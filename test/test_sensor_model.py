"""The beam sensor model: the table, log-space evaluation, scoring, downsampling."""
import numpy as np
import pytest
from helpers import corridor_map

from localization.core.geometry import compose
from localization.core.occupancy_map import OccupancyMap
from localization.core.raycast.exact import ExactRayCaster
from localization.core.scan import ScanData, downsample_scan
from localization.sensor_model import SensorModel


def test_table_shape_and_columns_normalised():
    sm = SensorModel()
    t = sm.sensor_model_table
    assert t.shape == (201, 201)
    assert np.allclose(t.sum(axis=0), 1.0)
    assert np.all(t > 0)
    # the peak of each column (away from the ends) is at z = d
    assert all(abs(np.argmax(t[:-1, d]) - d) <= 2 for d in range(20, 180))


def test_each_component_alone():
    sm = SensorModel()
    sm.alpha_hit, sm.alpha_short, sm.alpha_max, sm.alpha_rand = 1.0, 0.0, 0.0, 0.0
    t = sm.precompute_sensor_model()
    z = np.arange(201)
    g = np.exp(-0.5 * ((z - 100) / 8.0) ** 2)
    assert np.allclose(t[:, 100], g / g.sum())

    sm.alpha_hit, sm.alpha_short = 0.0, 1.0
    t = sm.precompute_sensor_model()
    d = 50
    ps = np.where(z <= d, 2.0 / d * (1 - z / d), 0.0)
    assert np.allclose(t[:, d], ps / ps.sum())
    assert np.all(t[d + 1:, d] == 0)

    sm.alpha_short, sm.alpha_max = 0.0, 1.0
    t = sm.precompute_sensor_model()
    assert np.all(t[200] == 1.0) and np.all(t[:200] == 0.0)

    sm.alpha_max, sm.alpha_rand = 0.0, 1.0
    t = sm.precompute_sensor_model()
    assert np.allclose(t, 1.0 / 201)


def test_attributes_rebuild_table_with_new_width():
    sm = SensorModel()
    sm.table_width, sm.sigma_hit = 51, 2.0
    assert sm.precompute_sensor_model().shape == (51, 51)
    assert np.allclose(sm.sensor_model_table.sum(axis=0), 1.0)


@pytest.fixture(scope="module")
def corridor_model():
    sm = SensorModel(ray_caster="exact")
    sm.set_map(corridor_map())
    return sm


def test_log_space_matches_plain_product(corridor_model):
    sm = corridor_model
    particles = np.array([[5.0, 1.5, 0.1], [4.0, 1.2, -0.3], [7.0, 2.0, 2.0]])
    obs = np.array([1.0, 2.0, 0.5, 3.0, 10.0, 0.2, 1.5, 0.9])
    w = sm.evaluate(particles, obs)
    angles = sm.default_angles(obs.size)
    d = np.rint(np.clip(ExactRayCaster(sm.map, sm.max_range).cast(particles, angles) / sm.map.resolution, 0, 200))
    z = np.rint(np.clip(obs / sm.map.resolution, 0, 200))
    plain = np.prod(sm.sensor_model_table[z.astype(int)[None, :], d.astype(int)], axis=1) ** (1 / 2.2)
    assert np.allclose(w, plain, rtol=1e-9)
    sm.squash_factor = 1.0
    plain1 = np.prod(sm.sensor_model_table[z.astype(int)[None, :], d.astype(int)], axis=1)
    assert np.allclose(sm.evaluate(particles, obs), plain1, rtol=1e-9)
    sm.squash_factor = 2.2


def test_many_beams_do_not_underflow(corridor_model):
    obs = np.full(2000, 10.0)
    w = corridor_model.evaluate(np.array([[5.0, 1.5, 0.0]]), obs)
    ll = corridor_model.log_likelihood(np.array([[5.0, 1.5, 0.0]]), obs)
    assert np.isfinite(ll[0]) and not np.isnan(w[0])


def test_true_scan_scores_far_above_shifted(maps_dir):
    m = OccupancyMap.from_yaml(maps_dir / "stata_basement.yaml")
    sm = SensorModel(laser_offset=(0.275, 0.0, 0.0), occupancy_map=m)
    truth = np.array([-6.0, 20.0, -2.24])
    angles = np.linspace(-2.356, 2.356, 100)
    obs = ExactRayCaster(m, 10.0).cast(compose(truth, [0.275, 0, 0])[None], angles)[0]
    particles = np.array([truth, truth + [0.5, 0, 0], truth + [0, 0.5, 0], truth + [0, 0, 0.2]])
    ll = sm.log_likelihood(particles, obs, angles)
    assert np.all(ll[0] > ll[1:] + 5.0), ll


def test_impossible_particles_get_zero_weight(corridor_model):
    particles = np.array([[5.0, 0.52, 0.0], [-1.0, 1.0, 0.0], [5.0, 1.5, 0.0]])  # in wall, off map, fine
    w = corridor_model.evaluate(particles, np.full(10, 1.0))
    assert w[0] == 0.0 and w[1] == 0.0 and w[2] > 0.0 and not np.any(np.isnan(w))


def test_downsampling_with_invalid_ranges():
    n = 1081
    ranges = np.linspace(1.0, 5.0, n)
    ranges[0], ranges[540], ranges[1080] = np.nan, np.inf, -1.0
    ranges[270] = 65.533  # Hokuyo error code above range_max
    ranges[810] = 0.004  # below range_min
    scan = downsample_scan(ScanData(0.0, ranges, -2.356, 2.356, 4.712 / 1080, 0.02, 30.0), 5)
    assert scan.ranges.size == 5
    assert np.allclose(scan.angles, [-2.356, -1.178, 0.0, 1.178, 2.356], atol=1e-3)
    assert np.all(np.isinf(scan.ranges[[0, 2, 4]]))
    assert np.isfinite(scan.ranges[1]) is np.False_ or scan.ranges[1] == np.inf  # 65.533 > 30
    assert np.isinf(scan.ranges[3])  # 0.004 < range_min
    full = downsample_scan(ScanData(0.0, ranges, -2.356, 2.356, 4.712 / 1080, 0.02, 30.0), 100)
    assert full.ranges.size == 100 and np.all(np.diff(full.angles) > 0)
    # invalid ranges count as max range: the sensor model maps them to z_max
    sm = SensorModel()
    sm.set_map(corridor_map())
    assert np.all(sm.to_cells(np.array([np.inf, np.nan, 1e9])) == 200)
