"""Large maps: the range table built per tile where the particles are (``core/raycast/tiled_table.py``),
checked on a small tiled map against the full table and the exact caster."""
from __future__ import annotations

import gc

import numpy as np
import pytest
from helpers import corridor_map

from localization.benchmarks.large_map import shift_to_tile, tiled_map
from localization.core.models.beam import BeamModel
from localization.core.occupancy_map import OccupancyMap
from localization.core.raycast import ExactRayCaster, LookupTableRayCaster, TiledLookupTableRayCaster, make_ray_caster
from localization.core.raycast.tiled_table import chessboard_clearance, chessboard_clearance_numpy


def small_tiled_map() -> OccupancyMap:
    """A room with a pillar and a box, tiled 2 x 2, with a yawed origin (as the Stata maps)."""
    data = np.full((50, 70), -1, dtype=np.int8)
    data[2:48, 2:68] = 0
    data[1, 1:69] = data[48, 1:69] = 100
    data[1:49, 1] = data[1:49, 68] = 100
    data[30:48, 50:68] = 100
    data[15:19, 15:19] = 100
    return tiled_map(OccupancyMap(data, 0.05, (3.0, -2.0, 0.3)), 2, 2)


@pytest.fixture(scope="module")
def casters():
    m = small_tiled_map()
    full = LookupTableRayCaster(m, 3.0, 72)
    tiled = TiledLookupTableRayCaster(m, 3.0, 72, tile=16)
    return m, full, tiled


def test_tiled_map_repeats_the_map_and_shifts_poses():
    m = corridor_map()
    big = tiled_map(m, 3, 2)
    assert big.data.shape == (2 * m.height, 3 * m.width) and big.resolution == m.resolution
    assert np.array_equal(big.data[m.height:, 2 * m.width:], m.data)
    pose = np.array([[2.0, 1.5, 0.7]])
    moved = shift_to_tile(m, pose, 2, 1)
    assert np.allclose(big.world_to_grid_continuous(moved[:, :2]) - m.world_to_grid_continuous(pose[:, :2]),
                       [2 * m.width, m.height]) and moved[0, 2] == 0.7


def test_clearance_kernel_equals_scipy():
    rng = np.random.default_rng(0)
    b = rng.random((120, 90)) < 0.02
    b[0] = b[-1] = True
    b[:, 0] = b[:, -1] = True
    b[10:110, 5:85] = False  # a wide open area: distances up to ~40
    assert np.array_equal(chessboard_clearance(b), chessboard_clearance_numpy(b))
    big = np.zeros((700, 30), dtype=bool)
    big[0] = True  # distances beyond 255 saturate
    assert np.array_equal(chessboard_clearance(big), chessboard_clearance_numpy(big))
    assert chessboard_clearance(big).max() == 255


def test_nothing_is_built_up_front_and_queries_build_only_their_tiles(casters):
    m = small_tiled_map()
    tiled = TiledLookupTableRayCaster(m, 3.0, 72, tile=16)
    assert tiled.tiles_built == 0 and tiled.rows_built == 0
    poses = m.sample_free_poses(5, np.random.default_rng(1))
    tiled.cast(poses, np.linspace(-2.0, 2.0, 9))
    assert 1 <= tiled.tiles_built <= 5
    assert set(np.flatnonzero(tiled.built & (np.diff(tiled.tile_start) > 0))) == set(tiled.tiles_of(poses))


def test_tiled_rows_equal_the_full_table(casters):
    m, full, tiled = casters
    table = tiled.build_table()
    assert tiled.tiles_built == int(np.count_nonzero(np.diff(tiled.tile_start)))
    rows, cols = np.nonzero(m.free)
    assert np.array_equal(table[tiled.index[rows, cols]], full.table[full.index[rows, cols]])
    # each tile's rows are one contiguous block, in the tile's cells
    t = int(np.argmax(np.diff(tiled.tile_start)))
    tr, tc = divmod(t, tiled.tiles_shape[1])
    block = tiled.index[tr * 16:(tr + 1) * 16, tc * 16:(tc + 1) * 16]
    assert np.array_equal(np.sort(block[block >= 0]), np.arange(tiled.tile_start[t], tiled.tile_start[t + 1]))


def test_tiled_queries_equal_the_full_table_and_the_exact_caster():
    m = small_tiled_map()
    full = LookupTableRayCaster(m, 3.0, 72)
    tiled = TiledLookupTableRayCaster(m, 3.0, 72, tile=16)
    rng = np.random.default_rng(2)
    poses = m.sample_free_poses(400, rng)
    angles = np.linspace(-2.3, 2.3, 31)
    got = tiled.cast(poses, angles)
    assert np.array_equal(got, full.cast(poses, angles))
    assert np.allclose(tiled.cast_numpy(poses, angles), got, atol=1e-9)
    exact = ExactRayCaster(m, 3.0).cast(poses, angles)
    diff = np.abs(got - exact) / m.resolution
    assert np.median(diff) <= 1.0 and np.percentile(diff, 95) <= 3.0
    refined = TiledLookupTableRayCaster(m, 3.0, 72, tile=16, refine=1.0)
    assert np.mean(np.abs(refined.cast(poses, angles) - exact) < 1e-6) > 0.95  # the exact finish works too


def test_beam_model_builds_tiles_through_make_ray_caster():
    m = small_tiled_map()
    assert isinstance(make_ray_caster("lookup_table", m, 3.0, 72, lazy_cells=0), TiledLookupTableRayCaster)
    assert type(make_ray_caster("lookup_table", m, 3.0, 72, lazy_cells=m.data.size)) is LookupTableRayCaster
    lazy = BeamModel(ray_caster="lookup_table", range_table_lazy_cells=0, table_width=61)
    lazy.set_map(m)
    eager = BeamModel(ray_caster="lookup_table", table_width=61)
    eager.set_map(m)
    assert isinstance(lazy.ray_caster, TiledLookupTableRayCaster) and lazy.ray_caster.tiles_built <= 1
    rng = np.random.default_rng(3)
    particles = m.sample_free_poses(300, rng)
    ranges = rng.uniform(0.2, 3.0, 40)
    angles = np.linspace(-2.0, 2.0, 40)
    got = lazy.log_likelihood(particles, ranges, angles)  # the fused kernel: tiles built by prepare()
    assert np.array_equal(got, eager.log_likelihood(particles, ranges, angles))
    assert np.allclose(got, lazy.log_likelihood_numpy(particles, ranges, angles))
    offsets = np.column_stack([np.linspace(0, 0.04, 40), np.linspace(0, 0.01, 40), np.linspace(0, 0.02, 40)])
    deskewed = lazy.log_likelihood(particles, ranges, angles, offsets=offsets)  # a deskewed sweep, as the filter's
    assert np.array_equal(deskewed, eager.log_likelihood(particles, ranges, angles, offsets=offsets))
    assert np.allclose(deskewed, lazy.log_likelihood_numpy(particles, ranges, angles, offsets=offsets))


@pytest.mark.parametrize("resolution, radius", [(0.05, 0.15), (0.0504, 0.1252), (0.1, 0.35), (0.05, 0.0), (1.0, 3.3)])
def test_near_obstacle_equals_a_disk_dilation(resolution, radius):
    """``OccupancyMap.near_obstacle`` (row runs of the disk, fast on 20 M cells) is the dilation by the disk."""
    import math

    from scipy.ndimage import binary_dilation
    data = np.where(np.random.default_rng(4).random((60, 80)) < 0.03, 100, 0).astype(np.int8)
    m = OccupancyMap(data, resolution)
    reach = int(math.floor(radius / resolution + 1e-9))
    i, j = np.mgrid[-reach:reach + 1, -reach:reach + 1]
    disk = (i * i + j * j) * resolution ** 2 <= radius * radius + 1e-12
    assert np.array_equal(m.near_obstacle(radius), binary_dilation(m.occupied, structure=disk))


def test_the_localizer_takes_range_table_lazy_cells_on_both_map_paths():
    from localization.core.localizer import Localizer
    from localization.core.parameters import Parameters
    m = small_tiled_map()
    params = Parameters(range_table_lazy_cells=0, ray_caster="lookup_table", random_seed=0, num_particles=200)
    assert isinstance(Localizer(params).prepare_ray_caster(m), TiledLookupTableRayCaster)  # the node's path
    loc = Localizer(params)
    loc.set_map(m)
    assert isinstance(loc._pf.sensor_model.ray_caster, TiledLookupTableRayCaster)
    eager = Localizer(Parameters(ray_caster="lookup_table", random_seed=0, num_particles=200))
    eager.set_map(m)
    assert type(eager._pf.sensor_model.ray_caster) is LookupTableRayCaster  # small maps: the full table


def _rss_kb() -> int:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS"))


def test_released_tiles_give_memory_back_and_are_rebuilt_equal():
    m = tiled_map(small_tiled_map(), 4, 4)  # 16 x the room: a table of several MB
    full = LookupTableRayCaster(m, 3.0, 72)
    tiled = TiledLookupTableRayCaster(m, 3.0, 72, tile=16)
    TiledLookupTableRayCaster(small_tiled_map(), 3.0, 72, tile=16).build_table()  # compiled (or loaded) first
    gc.collect()  # earlier tests' garbage freed now, not during the measurement (it would hide the growth)
    gc.disable()
    try:
        before = _rss_kb()
        tiled.build_table()
        grown = _rss_kb() - before
        assert grown > 0.5 * tiled.table.nbytes / 1024  # the rows are resident once built
        everything = np.flatnonzero(tiled.built)
        assert tiled.release_tiles(everything) == np.count_nonzero(np.diff(tiled.tile_start))
        assert tiled.tiles_built == 0
        assert _rss_kb() - before < 0.3 * grown  # given back (whole pages inside each tile)
    finally:
        gc.enable()
    poses = m.sample_free_poses(300, np.random.default_rng(4))
    angles = np.linspace(-2.3, 2.3, 31)
    assert np.array_equal(tiled.cast(poses, angles), full.cast(poses, angles))  # rebuilt where needed, equal


def _seed_case(seed: int, lazy: bool, step: float, headings: int, beams: int, candidates: int):
    """(map, beam model (tiled table when ``lazy``), exact scan ranges and angles from a random free
    pose, seeding parameters) for the global-seeding tests."""
    from localization.core.filter.global_init import ScanSeedParams
    m = small_tiled_map()
    model = BeamModel(ray_caster="lookup_table", table_width=61, **({"range_table_lazy_cells": 0} if lazy else {}))
    model.set_map(m)
    truth = m.sample_free_poses(1, np.random.default_rng(seed))
    angles = np.linspace(-2.3, 2.3, 60)
    ranges = ExactRayCaster(m, 3.0).cast(truth, angles)[0]
    return m, model, ranges, angles, ScanSeedParams(global_seed_step=step, global_seed_headings=headings,
                                                    global_seed_beams=beams, global_seed_candidates=candidates)


def test_global_seed_on_a_tiled_table_keeps_only_the_tiles_it_had():
    from localization.core.filter.global_init import seed_from_scan
    m, lazy, ranges, angles, p = _seed_case(5, True, 0.2, 36, 30, 200)
    _, eager, _, _, _ = _seed_case(5, False, 0.2, 36, 30, 200)
    built_before = lazy.ray_caster.built.copy()
    got = seed_from_scan(m, lazy, ranges, angles, 500, np.random.default_rng(6), p, chunk=2000)
    assert np.array_equal(lazy.ray_caster.built, built_before)  # the lattice's tiles were given back
    want = seed_from_scan(m, eager, ranges, angles, 500, np.random.default_rng(6), p, chunk=2000)
    # the same candidates as with the full table (order of equal scores aside)
    assert np.allclose(np.sort(got.candidate_log_likelihood), np.sort(want.candidate_log_likelihood))
    assert got.lattice_poses == want.lattice_poses


def test_global_seed_running_top_k_equals_one_full_sort():
    """The lattice's best candidates kept chunk by chunk equal those of scoring it in one piece."""
    from localization.core.filter.global_init import seed_from_scan
    m, model, ranges, angles, p = _seed_case(7, False, 0.15, 24, 20, 300)
    small = seed_from_scan(m, model, ranges, angles, 200, np.random.default_rng(8), p, chunk=777)
    whole = seed_from_scan(m, model, ranges, angles, 200, np.random.default_rng(8), p, chunk=10**9)
    assert small.lattice_poses == whole.lattice_poses > 777 * 3
    assert np.array_equal(small.candidate_log_likelihood, whole.candidate_log_likelihood)
    assert np.array_equal(small.candidates, whole.candidates)  # ties in lattice order in both
    assert np.array_equal(small.poses, whole.poses)
