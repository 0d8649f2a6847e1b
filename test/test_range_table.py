"""The lookup-table ray caster (``range_table``), its fused sensor-model kernel, the compiled
motion/resampling kernels and the benchmark's smoke run.

Speed is measured by ``python -m localization.benchmarks.speed``, never asserted here."""
from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import corridor_map

from localization.core import paths
from localization.core.filter import mcl as mcl_module
from localization.core.filter.mcl import MonteCarloLocalizer
from localization.core.models import motion as motion_module
from localization.core.models.beam import BeamModel as SensorModel
from localization.core.models.motion import MotionModel
from localization.core.occupancy_map import OccupancyMap
from localization.core.parameters import Parameters
from localization.core.raycast import table_cache as table_cache_module
from localization.core.raycast.exact import ExactRayCaster
from localization.core.raycast.lookup_table import LookupTableRayCaster
from localization.core.raycast.table_cache import cache_file_name

ROOT = Path(__file__).resolve().parents[1]
BEAMS_270 = np.linspace(-2.356, 2.356, 60)


def uniform_free_poses(occupancy_map, n, rng):
    return occupancy_map.sample_free_poses(n, rng)


def room_map():
    """A small map with a room, a pillar, a diagonal wall, unknown space and an open edge."""
    data = np.full((80, 120), -1, dtype=np.int8)
    data[5:75, 5:115] = 0
    data[5, 5:115] = data[74, 5:115] = 100
    data[5:75, 5] = 100
    data[30:40, 50:58] = 100  # pillar
    for i in range(25):  # diagonal wall
        data[45 + i, 80 + i] = 100
    data[60:70, 20:30] = -1  # an unknown pocket inside
    return OccupancyMap(data, 0.05, (1.0, -2.0, 0.4))  # rotated origin, and the east side open (off-map)


@pytest.fixture(autouse=True)
def no_shared_tables():
    """Each test sees the disk cache, not tables another test left alive in this process."""
    table_cache_module.LIVE_TABLES.clear()
    yield
    table_cache_module.LIVE_TABLES.clear()


@pytest.fixture(scope="module")
def table_cache(tmp_path_factory):
    return tmp_path_factory.mktemp("range_tables")


@pytest.fixture(scope="module")
def stata_map(maps_dir):
    return OccupancyMap.from_yaml(maps_dir / "stata_basement.yaml")


@pytest.fixture(scope="module")
def stata_lut(stata_map, table_cache):
    """The Stata basement table with the default parameters (built once for this module)."""
    sm = SensorModel(ray_caster="exact", scan_theta_discretization=Parameters().scan_theta_discretization)
    sm.map = stata_map
    return LookupTableRayCaster.for_map(stata_map, sm.max_range, Parameters().scan_theta_discretization,
                                       cache_dir=table_cache)


# ------------------------------------------------------------------------------------ accuracy
def test_accuracy_against_the_exact_caster_on_stata(stata_map, stata_lut):
    rng = np.random.default_rng(7)
    poses = uniform_free_poses(stata_map, 3000, rng)
    exact = ExactRayCaster(stata_map, stata_lut.max_range)
    diff = np.abs(stata_lut.cast(poses, BEAMS_270) - exact.cast(poses, BEAMS_270)) / stata_map.resolution
    assert np.median(diff) <= 1.0
    assert np.percentile(diff, 95) <= 3.0


def test_table_is_the_exact_range_from_each_cell_centre(stata_map, stata_lut):
    rng = np.random.default_rng(8)
    rows = rng.integers(0, stata_lut.num_free, 300)
    cells = stata_map.free_cells[rows]
    k = stata_lut.theta_bins
    bins = rng.integers(0, k, 300)
    th = 2 * np.pi * bins / k
    exact = ExactRayCaster(stata_map, stata_lut.max_range)
    cells_exact = exact._cast_grid(cells[:, 1] + 1.5, cells[:, 0] + 1.5, np.cos(th), np.sin(th))
    stored = stata_lut.table[rows, bins] / stata_lut.units_per_cell
    # exact to the table's resolution, the exact diagonals (rays through lattice corners) included
    assert np.max(np.abs(stored - np.minimum(cells_exact, stata_lut.max_cells))) <= 1.0 / stata_lut.units_per_cell
    assert np.count_nonzero(bins % (k // 8) == 0) > 0


def test_exact_finish_matches_the_exact_caster(stata_map, stata_lut):
    refined = LookupTableRayCaster(stata_map, stata_lut.max_range, stata_lut.theta_bins, table=stata_lut.table,
                                   refine=1.0)
    rng = np.random.default_rng(9)
    poses = uniform_free_poses(stata_map, 1000, rng)
    exact = ExactRayCaster(stata_map, stata_lut.max_range).cast(poses, BEAMS_270)
    diff = np.abs(refined.cast(poses, BEAMS_270) - exact) / stata_map.resolution
    assert np.mean(diff < 1e-6) > 0.98  # the rest: thin obstacles both bins missed
    refined.use_numba = False  # the numpy fallback casts exactly
    assert np.allclose(refined.cast(poses[:50], BEAMS_270), exact[:50], rtol=0, atol=1e-9)
    with pytest.raises(ValueError):
        LookupTableRayCaster(stata_map, 1.0, 16, table=None, refine=-1.0)


@pytest.mark.parametrize("interpolation", ["line", "linear", "nearest"])
def test_compiled_cast_equals_the_numpy_reference(interpolation):
    m = room_map()
    caster = LookupTableRayCaster(m, 3.0, 64, interpolation=interpolation)
    rng = np.random.default_rng(1)
    poses = np.vstack([uniform_free_poses(m, 400, rng), [[1.0, -2.0, 0.0], [100.0, 100.0, 1.0]]])
    angles = np.concatenate([np.linspace(-np.pi, np.pi, 37), [0.0, 2 * np.pi / 64, 7.0, -7.0]])
    assert np.allclose(caster.cast(poses, angles), caster.cast_numpy(poses, angles), rtol=0, atol=1e-9)


@pytest.mark.parametrize("interpolation", ["line", "linear", "nearest"])
def test_small_map_accuracy_of_each_interpolation(interpolation):
    m = room_map()
    caster = LookupTableRayCaster(m, 3.0, 144, interpolation=interpolation)
    exact = ExactRayCaster(m, 3.0)
    rng = np.random.default_rng(2)
    poses = uniform_free_poses(m, 500, rng)
    diff = np.abs(caster.cast(poses, BEAMS_270) - exact.cast(poses, BEAMS_270)) / m.resolution
    assert np.median(diff) <= 1.0 and np.percentile(diff, 95) <= 3.0


def test_sensors_outside_free_space_see_zero_like_the_exact_caster():
    m = corridor_map()  # free between rows 10 and 50, unknown outside
    caster = LookupTableRayCaster(m, 4.0, 32)
    exact = ExactRayCaster(m, 4.0)
    occupied = m.grid_to_world(np.array([[50, 10]]))[0]
    unknown = m.grid_to_world(np.array([[50, 55]]))[0]
    poses = np.array([[*occupied, 0.3], [*unknown, 1.0], [-5.0, -5.0, 0.0], [50.0, 50.0, 2.0]])
    angles = np.linspace(-2, 2, 9)
    got = caster.cast(poses[:4], angles)
    assert np.array_equal(got, np.zeros((4, 9)))
    assert np.array_equal(exact.cast(poses[:4], angles), got)
    assert np.array_equal(caster.cast_numpy(poses[:4], angles), got)
    free = m.grid_to_world(np.array([[50, 30]]))[0]
    assert np.all(caster.cast([[*free, 0.0]], angles) > 0)


def test_non_finite_poses_see_zero_and_non_finite_angles_are_refused(tmp_path):
    m = corridor_map()
    caster = LookupTableRayCaster(m, 4.0, 32)
    free = m.grid_to_world(np.array([[50, 30]]))[0]
    poses = np.array([[np.nan, free[1], 0.0], [free[0], np.inf, 0.0], [*free, np.nan], [*free, np.inf], [*free, 0.5]])
    angles = np.linspace(-2, 2, 9)
    got = caster.cast(poses, angles)
    assert np.array_equal(got[:4], np.zeros((4, 9))) and np.all(got[4] > 0)
    assert np.array_equal(caster.cast_numpy(poses, angles), got)
    with pytest.raises(ValueError):
        caster.cast(poses, [0.0, np.nan])
    sm = SensorModel(ray_caster="exact", table_width=41)
    sm.set_map(m, caster)
    log_w = sm.log_likelihood(poses, np.full(9, 1.0), angles)
    assert np.isneginf(log_w[:2]).all() and np.isfinite(log_w[2:]).all()


def test_constructor_checks():
    m = corridor_map()
    with pytest.raises(ValueError):
        LookupTableRayCaster(m, 2.0, 4)
    with pytest.raises(ValueError):
        LookupTableRayCaster(m, 2.0, 16, interpolation="cubic")
    with pytest.raises(ValueError):
        LookupTableRayCaster(m, 2.0, 16, table=np.zeros((3, 16), dtype=np.uint16))


# ------------------------------------------------------------------------------------ the disk cache
def test_cache_round_trip_is_identical_and_used(tmp_path, monkeypatch):
    m = room_map()
    first = LookupTableRayCaster.for_map(m, 3.0, 48, cache_dir=tmp_path)
    assert not first.loaded_from_cache
    path = tmp_path / cache_file_name(m, 3.0, 48)
    assert first.cache_path == path and path.is_file()
    assert list(tmp_path.iterdir()) == [path]  # written atomically: no temporary left behind

    def no_build(self):
        raise AssertionError("the table was rebuilt although it is cached")
    monkeypatch.setattr(LookupTableRayCaster, "build_table", no_build)
    shared = LookupTableRayCaster.for_map(m, 3.0, 48, cache_dir=tmp_path)  # the first is still alive
    assert shared.table_source == "memory" and shared.table is first.table
    table_cache_module.LIVE_TABLES.clear()
    second = LookupTableRayCaster.for_map(m, 3.0, 48, cache_dir=tmp_path)
    assert second.loaded_from_cache and second.table_source == "disk" and second.cache_path == path
    assert second.table.dtype == np.uint16 and np.array_equal(first.table, second.table)
    poses = uniform_free_poses(m, 50, np.random.default_rng(0))
    assert np.array_equal(first.cast(poses, BEAMS_270), second.cast(poses, BEAMS_270))


def test_cached_table_is_mapped_copy_on_write(tmp_path):
    """A cached table is mapped from its file, not read into memory: an ordinary writable array whose writes
    never reach the file; a compressed member (a table saved by other means) is read as before."""
    import zipfile
    m = room_map()
    built = LookupTableRayCaster.for_map(m, 3.0, 48, cache_dir=tmp_path).table.copy()
    table_cache_module.LIVE_TABLES.clear()
    path = tmp_path / cache_file_name(m, 3.0, 48)
    loaded = table_cache_module.load_table(path, m, 3.0, 48)
    assert type(loaded) is np.ndarray and isinstance(loaded.base, np.memmap) and loaded.flags.writeable
    assert np.array_equal(loaded, built)
    loaded[0, 0] ^= 1
    with np.load(path) as data:
        assert np.array_equal(data["table"], built)  # the file is unchanged
    squeezed = tmp_path / "compressed.npz"
    with np.load(path) as data:
        np.savez_compressed(squeezed, table=data["table"], meta=data["meta"])
    with zipfile.ZipFile(squeezed) as zf:
        info = zf.getinfo("table.npy")
    assert info.compress_type == zipfile.ZIP_DEFLATED
    assert table_cache_module.mapped_member(squeezed, info) is None
    again = table_cache_module.load_table(squeezed, m, 3.0, 48)
    assert not isinstance(again.base, np.memmap) and np.array_equal(again, built)


def test_cache_key_covers_map_content_range_and_bins(tmp_path):
    m = room_map()
    other = OccupancyMap(m.data.copy(), m.resolution, m.origin)
    other.data[10, 10] = 100
    names = {cache_file_name(m, 3.0, 48), cache_file_name(m, 3.5, 48), cache_file_name(m, 3.0, 64),
             cache_file_name(other, 3.0, 48)}
    assert len(names) == 4
    assert f"v{table_cache_module.FORMAT_VERSION}" in cache_file_name(m, 3.0, 48)


def test_cache_dir_from_the_environment(tmp_path, monkeypatch):
    monkeypatch.setenv("LOCALIZATION_CACHE_DIR", str(tmp_path / "lut"))
    assert paths.cache_dir() == tmp_path / "lut"
    m = corridor_map()
    LookupTableRayCaster.for_map(m, 2.0, 16)
    assert (tmp_path / "lut" / cache_file_name(m, 2.0, 16)).is_file()
    monkeypatch.delenv("LOCALIZATION_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert paths.cache_dir() == tmp_path / "xdg" / "localization"
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert paths.cache_dir() == Path.home() / ".cache" / "localization"


def test_corrupt_or_unwritable_cache_only_costs_a_rebuild(tmp_path, caplog):
    m = corridor_map()
    path = tmp_path / cache_file_name(m, 2.0, 16)
    path.write_bytes(b"not a table")
    with caplog.at_level(logging.WARNING):
        caster = LookupTableRayCaster.for_map(m, 2.0, 16, cache_dir=tmp_path)
    assert not caster.loaded_from_cache and "rebuilding" in caplog.text
    table_cache_module.LIVE_TABLES.clear()
    assert LookupTableRayCaster.for_map(m, 2.0, 16, cache_dir=tmp_path).table_source == "disk"  # rewritten
    path.write_bytes(path.read_bytes()[:500])  # a truncated zip
    table_cache_module.LIVE_TABLES.clear()
    assert LookupTableRayCaster.for_map(m, 2.0, 16, cache_dir=tmp_path).table_source == "built"
    blocked = tmp_path / "a_file"
    blocked.write_text("")
    table_cache_module.LIVE_TABLES.clear()
    caster = LookupTableRayCaster.for_map(m, 2.0, 16, cache_dir=blocked / "sub")  # cannot mkdir under a file
    assert not caster.loaded_from_cache and caster.cache_path is None


def test_sensor_model_builds_the_table_with_the_configured_bins(tmp_path, monkeypatch):
    monkeypatch.setenv("LOCALIZATION_CACHE_DIR", str(tmp_path))
    sm = SensorModel(ray_caster="lookup_table", scan_theta_discretization=40, occupancy_map=corridor_map())
    assert isinstance(sm.ray_caster, LookupTableRayCaster) and sm.ray_caster.theta_bins == 40
    assert sm.ray_caster.max_range == pytest.approx(sm.max_range)


# ------------------------------------------------------------------------------------ fused likelihood
@pytest.mark.parametrize("offset, scale", [((0.0, 0.0, 0.0), 1.0), ((0.275, 0.03, 0.1), 1.0), ((0.2, 0.0, 0.0), 1.3)])
def test_fast_log_likelihood_equals_the_generic_path(tmp_path, monkeypatch, offset, scale):
    monkeypatch.setenv("LOCALIZATION_CACHE_DIR", str(tmp_path))
    m = room_map()
    sm = SensorModel(ray_caster="lookup_table", scan_theta_discretization=72, laser_offset=offset,
                     lidar_scale_to_map_scale=scale, table_width=61, occupancy_map=m)
    rng = np.random.default_rng(3)
    particles = np.vstack([uniform_free_poses(m, 300, rng), rng.uniform(-3, 9, (60, 3))])  # some off the map
    angles = np.linspace(-2.3, 2.3, 45)
    observation = sm.expected_ranges(particles[:1], angles)[0] + rng.normal(0, 0.05, angles.size)
    observation[::7] = np.inf
    fast = sm.log_likelihood(particles, observation, angles)
    generic = sm.log_likelihood_numpy(particles, observation, angles)
    assert np.array_equal(np.isneginf(fast), np.isneginf(generic)) and np.isneginf(fast).any()
    finite = np.isfinite(generic)
    assert np.allclose(fast[finite], generic[finite], rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("interpolation", ["line", "linear", "nearest"])
def test_fused_kernel_equals_the_numpy_reference_for_every_interpolation(tmp_path, monkeypatch, interpolation):
    """The fused kernel runs the table passes in its own body: every interpolation, rigid and deskewed sweeps,
    gives the numpy reference's likelihoods (particles off the map, in walls and blind included)."""
    monkeypatch.setenv("LOCALIZATION_CACHE_DIR", str(tmp_path))
    m = room_map()
    sm = SensorModel(ray_caster="lookup_table", scan_theta_discretization=72, laser_offset=(0.2, 0.02, 0.05),
                     table_width=61, occupancy_map=m)
    sm.ray_caster.interpolation = interpolation
    rng = np.random.default_rng(11)
    particles = np.vstack([uniform_free_poses(m, 300, rng), rng.uniform(-3, 9, (60, 3))])
    angles = np.linspace(-2.3, 2.3, 45)
    observation = sm.expected_ranges(particles[:1], angles)[0] + rng.normal(0, 0.05, angles.size)
    observation[::7] = np.inf
    offsets = np.column_stack([np.linspace(-0.04, 0.04, 45), np.linspace(0.01, -0.01, 45), np.linspace(0, 0.02, 45)])
    for sweep in (None, offsets):
        fast = sm.log_likelihood(particles, observation, angles, offsets=sweep)
        ref = sm.log_likelihood_numpy(particles, observation, angles, offsets=sweep)
        assert np.array_equal(np.isneginf(fast), np.isneginf(ref)) and np.isneginf(fast).any()
        finite = np.isfinite(ref)
        assert finite.sum() > 200
        np.testing.assert_allclose(fast[finite], ref[finite], rtol=1e-12, atol=1e-9)


def test_numpy_fallback_of_the_fused_sums_matches(tmp_path):
    m = room_map()
    caster = LookupTableRayCaster.for_map(m, 3.0, 72, cache_dir=tmp_path)
    sm = SensorModel(ray_caster="exact", table_width=61, laser_offset=(0.1, 0.0, 0.0))
    sm.set_map(m, caster)
    rng = np.random.default_rng(4)
    particles = uniform_free_poses(m, 200, rng)
    angles = np.linspace(-2, 2, 30)
    observation = sm.expected_ranges(particles[:1], angles)[0]
    compiled = sm.log_likelihood(particles, observation, angles)
    caster.use_numba = False  # the beam model falls back to numpy over the caster's numpy cast
    assert np.allclose(sm.log_likelihood(particles, observation, angles), compiled, rtol=1e-12, atol=1e-9)


# ------------------------------------------------------------------------------------ motion / resampling kernels
@pytest.mark.parametrize("odometry", [[0.1, 0.02, 0.3], [0.0, 0.0, 0.0], [-0.05, 0.0, -3.0]])
@pytest.mark.parametrize("deterministic", [False, True])
def test_compiled_motion_update_equals_the_numpy_code(monkeypatch, odometry, deterministic):
    particles = np.random.default_rng(0).uniform(-4, 4, (2000, 3))
    compiled = MotionModel(rng=3, deterministic=deterministic).evaluate(particles, odometry)
    in_place = particles.copy()
    MotionModel(rng=3, deterministic=deterministic).evaluate(in_place, odometry, out=in_place)
    monkeypatch.setattr(motion_module, "_move_kernel", None)
    plain = MotionModel(rng=3, deterministic=deterministic).evaluate(particles, odometry)
    assert np.allclose(compiled, plain, rtol=0, atol=1e-12) and np.array_equal(compiled, in_place)


@pytest.mark.parametrize("n", [1, 2, 7, 3000])
@pytest.mark.parametrize("roughening", [(0.01, 0.01, 0.005), (0.0, 0.0, 0.0)])
def test_compiled_resampling_equals_the_numpy_code(monkeypatch, n, roughening):
    rng = np.random.default_rng(n)
    particles = rng.uniform(-4, 4, (n, 3))
    weights = rng.exponential(size=n) ** 4
    weights[rng.random(n) < 0.3] = 0.0
    weights = weights / weights.sum() if weights.sum() > 0 else np.full(n, 1.0 / n)
    results = []
    for kernel in (mcl_module.resample_kernel, None):
        monkeypatch.setattr(mcl_module, "resample_kernel", kernel)
        f = MonteCarloLocalizer(MotionModel(), SensorModel(), n, roughening=roughening, rng=11)
        f.particles = particles.copy()
        f.resample(weights)
        results.append((f.particles, f.log_weights))
    assert np.array_equal(results[0][0], results[1][0]) and np.array_equal(results[0][1], results[1][1])


# ------------------------------------------------------------------------------------ the benchmark
def test_bench_quick_json_prints_the_keys(tmp_path):
    env = dict(os.environ, LOCALIZATION_CACHE_DIR=str(tmp_path / "user-cache"))
    out = subprocess.run([sys.executable, "-m", "localization.benchmarks.speed", "--quick", "--json"], cwd=ROOT,
                         env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)
    for key in ("workloads", "init_cold_s", "init_cached_s", "peak_rss_mb", "fast_vs_exact"):
        assert key in result
    assert result["workloads"]
    for w in result["workloads"]:
        for key in ("particles", "beams", "raycast_ms_median", "sensor_update_ms_median", "sensor_update_ms_p95",
                    "motion_update_ms_median", "rays_per_s", "exact_raycast_ms_median"):
            assert isinstance(w[key], (int, float)) and w[key] > 0
    assert set(result["fast_vs_exact"]) >= {"median_abs_cells", "p95_abs_cells"}
    assert result["init_cold"]["table_from_cache"] is False and result["init_cached"]["table_from_cache"] is True
    assert result["cold_jit"] is False and result["large_map"]["cold_jit"] is False  # --quick: numba's own cache
    assert not (tmp_path / "user-cache").exists()  # the benchmark keeps its tables to itself
    big = result["large_map"]  # the 3 x 3 tiled basement, in the same run
    assert big["cells"] >= 20_000_000 and big["caster"] == "TiledLookupTableRayCaster"
    for key in ("init_cold_s", "init_cached_s", "peak_rss_mb", "ct_mean_m", "single_ct_mean_m"):
        assert isinstance(big[key], float) and 0 < big[key] < 1e4
