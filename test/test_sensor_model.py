"""The beam sensor model: the table, log-space evaluation, scoring, downsampling."""
import numpy as np
import pytest
from helpers import corridor_map

from localization.core.geometry import compose
from localization.core.models.beam import BeamModel as SensorModel
from localization.core.occupancy_map import OccupancyMap
from localization.core.raycast.exact import ExactRayCaster
from localization.core.scan import ScanData, downsample_scan


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
    sm.table_width, sm.sigma_hit = 51, 0.1
    assert sm.params.table_width == 51 and sm.params.sigma_hit == 0.1  # the course's attributes are the params
    assert sm.precompute_sensor_model().shape == (51, 51)
    assert np.allclose(sm.sensor_model_table.sum(axis=0), 1.0)
    wide = sm.sensor_model_table[25, 25]
    sm.sigma_hit = 0.05  # a write drops the tables: rebuilt on use, 1 cell wide now (was 2)
    assert np.argmax(sm.sensor_model_table[:, 25]) == 25 and sm.sensor_model_table[25, 25] > 1.5 * wide


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
    # a 30 m lidar: z_max is capped at the table's reach, the numbers of the table in map cells (0.05 m here)
    assert np.array_equal(sm.evaluate(particles, obs, range_max=30.0), w)
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


def test_to_cells_rounds_and_clips_as_its_definition():
    """Table indices: rint of clip(range / resolution, 0, k), NaN as k; every finite, infinite and NaN range."""
    sm = SensorModel()
    rng = np.random.default_rng(4)
    ranges = np.concatenate([rng.uniform(-1.0, 12.0, 20000), [np.nan, np.inf, -np.inf, -0.0, 0.0]])
    for k in (200, 120, 7):
        cells = ranges * (1.0 / sm.params.table_resolution)
        expected = np.rint(np.clip(np.where(np.isnan(cells), k, cells), 0, k)).astype(np.intp)
        assert np.array_equal(sm.to_cells(ranges, k), expected)
    assert sm.to_cells(3.3) == np.rint(3.3 / sm.params.table_resolution)  # a single range too


# ------------------------------------------------------------------ z_max: the sensor's range, in metres
LIDAR_5_6 = 5.6  # m: a short-range lidar (the UoB Pioneer bags' range_max)


def long_corridor():
    """25 m x 2 m (0.05 m cells): looking along it, the far wall is > 10 m away."""
    return corridor_map(width_cells=500, height_cells=60, wall_rows=(10, 50))


def hand_max_entry(sm, k: int) -> float:
    """The table entry (z = k, d = k) of the module docstring, for z_max row k: a max-range reading where
    the particle expects no wall within z_max."""
    p = sm.params
    sigma = p.sigma_hit / p.table_resolution
    z = np.arange(k + 1.0)
    g = np.exp(-0.5 * ((z - k) / sigma) ** 2)
    short = 2.0 / k * (1.0 - z / k)
    column = p.alpha_hit + p.alpha_short * short.sum() + p.alpha_max + p.alpha_rand * (k + 1) / k
    return (p.alpha_hit * g[-1] / g.sum() + p.alpha_max + p.alpha_rand / k) / column


def test_a_short_lidars_no_return_beams_are_max_range_readings_at_its_range_max():
    m = long_corridor()
    sm = SensorModel(ray_caster="exact", laser_offset=(0.0, 0.0, 0.0), occupancy_map=m)
    assert sm.params.laser_max_range <= 0 and sm.table_range == pytest.approx(10.0)
    k = sm.z_max_row(LIDAR_5_6)
    assert k == 112 and sm.max_range_for(LIDAR_5_6) == LIDAR_5_6 and sm.max_range == pytest.approx(10.0)
    angles = np.array([-0.02, 0.0, 0.02])
    no_return = np.array([np.inf, np.nan, 7.0])  # no return, a bad value, beyond range_max: all "max range"
    open_space = np.array([[2.0, 1.5, 0.0]])  # looking along the corridor: the far wall 23 m away
    ll = sm.log_likelihood(open_space, no_return, angles, range_max=LIDAR_5_6)
    want = 3 * np.log(hand_max_entry(sm, 112)) / sm.params.squash_factor
    assert ll[0] == pytest.approx(want, rel=1e-12)  # p_max at 5.6 m, not a 10 m table entry
    assert ll[0] != pytest.approx(3 * np.log(sm.sensor_model_table[200, 200]) / sm.params.squash_factor)
    assert sm.log_likelihood_numpy(open_space, no_return, angles, range_max=LIDAR_5_6)[0] == pytest.approx(want)
    # a particle that would see the end wall 3 m ahead, where the scan says no return, is less likely
    wall_ahead = np.array([[21.95, 1.5, 0.0]])
    assert ExactRayCaster(m, 10.0).cast(wall_ahead, angles)[0] == pytest.approx(3.0, abs=0.06)
    both = sm.log_likelihood(np.vstack([open_space, wall_ahead]), no_return, angles, range_max=LIDAR_5_6)
    assert both[1] < both[0] - 0.5
    # expected ranges between 5.6 m and 10 m clip to z_max too: a wall 8 m ahead is "open space" for this lidar
    eight = np.array([[16.95, 1.5, 0.0]])
    assert sm.log_likelihood(eight, no_return, angles, range_max=LIDAR_5_6)[0] == pytest.approx(want)


def test_z_max_resolution_rules():
    sm = SensorModel(laser_offset=(0.0, 0.0, 0.0))
    reach = sm.table_range
    assert sm.max_range_for(None) == pytest.approx(reach)  # no scan: the table's reach
    assert sm.max_range_for(30.0) == pytest.approx(reach)  # a 30 m lidar: capped at the table's reach
    assert sm.max_range_for(float("nan")) == pytest.approx(reach) and sm.max_range_for(-1.0) == pytest.approx(reach)
    fixed = SensorModel(laser_max_range=4.0)
    assert fixed.max_range_for(5.6) == 4.0 and fixed.z_max_row(5.6) == 80  # the parameter wins over the scan
    scaled = SensorModel(lidar_scale_to_map_scale=0.5)  # lidar metres -> map metres
    assert scaled.max_range_for(30.0) == pytest.approx(2 * reach) and scaled.z_max_row(30.0) == 200
    assert scaled.z_max_row(5.6) == 56
    coarse = SensorModel(table_resolution=0.1, table_width=101)  # 10 m in 0.1 m table cells, whatever the map's
    assert coarse.to_cells(np.array([1.0, 2.55, np.inf])).tolist() == [10, 26, 100]
    assert coarse.sensor_model_table.shape == (101, 101) and coarse.z_max_row(5.6) == 56


def test_the_table_is_in_metres_whatever_the_maps_resolution():
    """The same corridor at 0.05 and 0.1 m/cell: the same log-likelihoods (table cells of 0.05 m)."""
    fine = corridor_map(width_cells=200, height_cells=60, wall_rows=(10, 50), resolution=0.05)
    coarse = corridor_map(width_cells=100, height_cells=30, wall_rows=(5, 25), resolution=0.1)
    angles = np.linspace(-1.5, 1.5, 31)
    pose = np.array([[4.02, 1.52, 0.1]])
    models = [SensorModel(ray_caster="exact", laser_offset=(0.0, 0.0, 0.0), occupancy_map=m) for m in (fine, coarse)]
    obs = ExactRayCaster(fine, 10.0).cast(pose, angles)[0]
    lls = [sm.log_likelihood(pose + [[0.1, 0.0, 0.0]], obs, angles, range_max=LIDAR_5_6)[0] for sm in models]
    assert models[0].table_range == models[1].table_range == pytest.approx(10.0)
    assert lls[0] == pytest.approx(lls[1], rel=0.05)


def test_fused_kernel_equals_numpy_with_a_short_z_max(tmp_path, monkeypatch):
    monkeypatch.setenv("LOCALIZATION_CACHE_DIR", str(tmp_path))
    m = long_corridor()
    sm = SensorModel(ray_caster="lookup_table", scan_theta_discretization=36, laser_offset=(0.275, 0.01, 0.02),
                     lidar_scale_to_map_scale=0.99, occupancy_map=m)
    rng = np.random.default_rng(3)
    particles = np.column_stack([rng.uniform(-0.5, 25.5, 400), rng.uniform(0.3, 2.7, 400), rng.uniform(-3, 3, 400)])
    angles = np.linspace(-2.35, 2.35, 60)
    obs = sm.expected_ranges(particles[:1], angles)[0] + rng.normal(0.0, 0.05, angles.size)
    obs[::9] = np.inf
    for range_max in (LIDAR_5_6, 30.0, None):
        fast = sm.log_likelihood(particles, obs, angles, range_max=range_max)
        ref = sm.log_likelihood_numpy(particles, obs, angles, range_max=range_max)
        assert np.array_equal(np.isneginf(fast), np.isneginf(ref)) and np.isfinite(ref).sum() > 100
        np.testing.assert_allclose(fast[np.isfinite(ref)], ref[np.isfinite(ref)], rtol=1e-9, atol=1e-9)


def test_each_weight_of_the_fused_kernel_is_that_particle_s_own_sum_bit_for_bit(tmp_path, monkeypatch):
    """The kernel sums four particles side by side: every weight equals that of the particle weighed alone,
    bit for bit, whatever its place in the cloud and with impossible particles (off the map, in a wall,
    NaN) among them."""
    monkeypatch.setenv("LOCALIZATION_CACHE_DIR", str(tmp_path))
    m = long_corridor()
    sm = SensorModel(ray_caster="lookup_table", scan_theta_discretization=36, laser_offset=(0.275, 0.01, 0.02),
                     occupancy_map=m)
    rng = np.random.default_rng(8)
    particles = np.column_stack([rng.uniform(0.5, 24.5, 203), rng.uniform(0.4, 2.6, 203), rng.uniform(-3, 3, 203)])
    particles[[1, 6, 7, 13, 100]] = [[-3.0, 1.5, 0.0], [6.0, 0.02, 0.0], [30.0, 1.5, 0.0], [np.nan, 1.5, 0.0],
                                     [6.0, -0.5, 1.0]]
    angles = np.linspace(-2.35, 2.35, 61)
    obs = sm.expected_ranges(particles[:1], angles)[0] + rng.normal(0.0, 0.05, angles.size)
    obs[::9] = np.inf
    together = sm.log_likelihood(particles, obs, angles, range_max=LIDAR_5_6).copy()
    alone = np.array([sm.log_likelihood(p[None], obs, angles, range_max=LIDAR_5_6)[0] for p in particles])
    assert np.isneginf(together).sum() >= 4 and np.isfinite(together).sum() > 150
    assert np.array_equal(together.view(np.int64), alone.view(np.int64))
    for start in range(1, 4):  # the groups of four start elsewhere in the cloud: the same weights
        np.testing.assert_array_equal(sm.log_likelihood(particles[start:], obs, angles, range_max=LIDAR_5_6),
                                      together[start:])


def test_wall_depth_scores_a_return_as_ending_that_far_behind_the_free_space_edge(tmp_path, monkeypatch):
    """map_wall_depth o: a return z is scored as s·z − o; returns at z_max and no-returns stay max-range
    readings; the fused kernel equals its numpy reference with it."""
    monkeypatch.setenv("LOCALIZATION_CACHE_DIR", str(tmp_path))
    m = long_corridor()
    kw = {"ray_caster": "lookup_table", "scan_theta_discretization": 36, "laser_offset": (0.275, 0.01, 0.02),
          "occupancy_map": m}
    deep = SensorModel(lidar_scale_to_map_scale=0.99, map_wall_depth=0.03, **kw)
    flat = SensorModel(lidar_scale_to_map_scale=0.99, **kw)
    k = deep.z_max_row(LIDAR_5_6)
    z = np.array([0.01, 1.0, 2.5, 5.0, LIDAR_5_6, np.inf, np.nan])
    rows = deep.measured_to_cells(z, k)
    assert rows.tolist() == flat.to_cells(np.array([0.0, 0.96, 2.445, 4.92, 0, 0, 0]), k)[:4].tolist() + [k, k, k]
    assert rows.tolist() != flat.measured_to_cells(z, k).tolist()
    rng = np.random.default_rng(5)
    particles = np.column_stack([rng.uniform(0.5, 24.5, 300), rng.uniform(0.6, 2.4, 300), rng.uniform(-3, 3, 300)])
    angles = np.linspace(-2.35, 2.35, 60)
    obs = deep.expected_ranges(particles[:1], angles)[0] + rng.normal(0.0, 0.03, angles.size)
    obs[::7] = np.inf
    fast = deep.log_likelihood(particles, obs, angles, range_max=LIDAR_5_6)
    ref = deep.log_likelihood_numpy(particles, obs, angles, range_max=LIDAR_5_6)
    assert np.isfinite(ref).sum() > 100
    np.testing.assert_allclose(fast[np.isfinite(ref)], ref[np.isfinite(ref)], rtol=1e-9, atol=1e-9)
    # a scan whose returns end 3 cm behind the edge fits the true pose better with the depth than without
    true = particles[:1]
    seen = deep.expected_ranges(true, angles)[0]
    behind = np.where(seen < LIDAR_5_6 - 0.1, (seen + 0.03) / 0.99, np.inf)
    assert deep.log_likelihood(true, behind, angles, range_max=LIDAR_5_6)[0] > \
        flat.log_likelihood(true, behind, angles, range_max=LIDAR_5_6)[0]


def _window_scene(**kw):
    """A corridor, a cloud near (6, 1.5, 0) and a scan from there whose beams 20-27 pass through a window: they
    read 0.4 m longer than the wall the map has."""
    m = long_corridor()
    sm = SensorModel(ray_caster="lookup_table", scan_theta_discretization=36, laser_offset=(0.275, 0.0, 0.0),
                     beam_skip_distance=0.15, occupancy_map=m, **kw)
    rng = np.random.default_rng(11)
    particles = np.column_stack([rng.normal(6.0, 0.05, 300), rng.normal(1.5, 0.05, 300), rng.normal(0.0, 0.02, 300)])
    angles = np.linspace(-2.35, 2.35, 60)
    clean = sm.expected_ranges(np.array([[6.0, 1.5, 0.0]]), angles)[0] + rng.normal(0.0, 0.02, angles.size)
    window = clean.copy()
    window[20:28] += 0.4
    return sm, particles, angles, clean, window


@pytest.mark.parametrize("deskew", [False, True])
def test_beam_skipping_kernel_equals_the_numpy_reference(tmp_path, monkeypatch, deskew):
    monkeypatch.setenv("LOCALIZATION_CACHE_DIR", str(tmp_path))
    sm, particles, angles, _, window = _window_scene(do_beamskip=True, beam_skip_max_spread=100.0)  # outliers below
    particles[:5] = [[-3.0, 1.5, 0.0], [6.0, 0.02, 0.0], [6.0, 1.5, 0.0], [30.0, 1.5, 0.0], [np.nan, 1.5, 0.0]]
    offsets = np.column_stack([np.linspace(0.0, 0.05, 60), np.zeros(60), np.linspace(0.0, 0.01, 60)]) if deskew \
        else None
    fast = sm.log_likelihood(particles, window, angles, offsets, range_max=8.0)
    used = sm.last_beams_used
    ref = sm.log_likelihood_numpy(particles, window, angles, offsets, range_max=8.0)
    assert sm.last_beams_used == used and 40 <= used <= 60 - 8  # the window's beams (at least) left out
    assert np.array_equal(np.isneginf(fast), np.isneginf(ref)) and np.isfinite(ref).sum() >= 295
    np.testing.assert_allclose(fast[np.isfinite(ref)], ref[np.isfinite(ref)], rtol=1e-12, atol=1e-12)


def test_beam_skipping_leaves_a_window_out_of_every_particle_s_weight(tmp_path, monkeypatch):
    """Readings through a window (longer than any particle expects) favour the particles expecting the longest
    range; skipped, they weigh nothing: the weights are those of the scan without them."""
    monkeypatch.setenv("LOCALIZATION_CACHE_DIR", str(tmp_path))
    sm, particles, angles, clean, window = _window_scene(do_beamskip=True)
    plain, _, _, _, _ = _window_scene()
    skipped = sm.log_likelihood(particles, window, angles, range_max=8.0)
    used = sm.last_beams_used
    kept = np.ones(angles.size, dtype=bool)
    kept[20:28] = False
    on_the_rest = sm.log_likelihood(particles, window[kept], angles[kept], range_max=8.0)
    assert sm.last_beams_used == used >= kept.sum() - 3  # the same few grazing beams skipped, not the window
    np.testing.assert_allclose(skipped, on_the_rest, rtol=1e-12, atol=1e-12)
    unskipped = plain.log_likelihood(particles, window, angles, range_max=8.0)
    rel = lambda w: w - w.max()  # noqa: E731 - relative log weights
    assert np.abs(rel(unskipped) - rel(plain.log_likelihood(particles, window[kept], angles[kept],
                                                            range_max=8.0))).max() > 0.5  # the window moves them


def test_beam_skipping_uses_every_beam_when_the_cloud_explains_too_few(tmp_path, monkeypatch):
    monkeypatch.setenv("LOCALIZATION_CACHE_DIR", str(tmp_path))
    sm, particles, angles, _, window = _window_scene(do_beamskip=True, beam_skip_error_threshold=0.1)
    everything, _, _, _, _ = _window_scene()
    out = sm.log_likelihood(particles, window, angles, range_max=8.0)  # 8 of 60 skipped would be >= 10 %: all used
    assert sm.last_beams_used == angles.size
    np.testing.assert_allclose(out, everything.log_likelihood(particles, window, angles, range_max=8.0), rtol=1e-12)
    spread = particles.copy()
    spread[:, 0] = np.linspace(1.0, 24.0, len(spread))  # along the whole corridor: no beam has a majority
    assert np.isfinite(sm.log_likelihood(spread, window, angles, range_max=8.0)).all()
    assert sm.last_beams_used == angles.size


def test_beam_skipping_applies_only_to_a_cloud_of_one_hypothesis(tmp_path, monkeypatch):
    """Two clusters 3 m apart (a global start narrowing down): the window's beams are minority beams for both, and
    a beam only the right cluster explains would be too; nothing is skipped until the cloud is one."""
    from dataclasses import replace

    from localization.core.models.sensor import skips_beams
    monkeypatch.setenv("LOCALIZATION_CACHE_DIR", str(tmp_path))
    sm, particles, angles, _, window = _window_scene(do_beamskip=True)
    plain, _, _, _, _ = _window_scene()
    two = np.vstack([particles[:150], particles[150:] + [3.0, 0.0, 0.0]])
    on, off = sm.params, replace(sm.params, do_beamskip=False)  # beam_skip_max_spread 1 m
    assert not skips_beams(two, on) and skips_beams(particles, on)
    assert not skips_beams(particles, off) and not skips_beams(np.full((3, 3), np.nan), on)
    np.testing.assert_array_equal(sm.log_likelihood(two, window, angles, range_max=8.0),
                                  plain.log_likelihood(two, window, angles, range_max=8.0))
    assert sm.last_beams_used == angles.size
    sm.log_likelihood(particles, window, angles, range_max=8.0)
    assert sm.last_beams_used <= angles.size - 8


def test_the_exact_finish_of_deskewed_beams_equals_the_numpy_reference(tmp_path, monkeypatch):
    """lookup_table_exact with per-beam origins (deskew): coarse heading bins make the table's estimate overshoot
    near corners and a beam's origin may lie in a wall for a particle hugging one; the compiled exact finish
    still gives the exact cast of the numpy reference."""
    monkeypatch.setenv("LOCALIZATION_CACHE_DIR", str(tmp_path))
    m = long_corridor()
    sm = SensorModel(ray_caster="lookup_table_exact", scan_theta_discretization=36,
                     laser_offset=(0.275, 0.01, 0.02), occupancy_map=m)
    rng = np.random.default_rng(3)
    particles = np.column_stack([rng.uniform(5, 7, 400), rng.uniform(0.3, 2.7, 400), rng.uniform(-0.3, 0.3, 400)])
    angles = np.linspace(-2.35, 2.35, 60)
    obs = sm.expected_ranges(particles[:1], angles)[0] + rng.normal(0.0, 0.05, angles.size)
    obs[::9] = np.inf
    offsets = np.column_stack([np.linspace(0.0, 0.05, 60), np.zeros(60), np.linspace(0.0, 0.01, 60)])
    fast = sm.log_likelihood(particles, obs, angles, offsets, range_max=LIDAR_5_6)
    ref = sm.log_likelihood_numpy(particles, obs, angles, offsets, range_max=LIDAR_5_6)
    assert np.array_equal(np.isneginf(fast), np.isneginf(ref)) and np.isfinite(ref).sum() > 300
    np.testing.assert_allclose(fast[np.isfinite(ref)], ref[np.isfinite(ref)], rtol=1e-9, atol=1e-9)
