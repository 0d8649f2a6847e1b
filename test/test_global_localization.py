"""Global localization seeded by the scan (``localization.core.filter.global_init``)."""
from __future__ import annotations

import logging

import numpy as np
import pytest

from localization.benchmarks import robustness as RB
from localization.core.filter.global_init import (
    ScanSeedParams,
    lattice_poses,
    lattice_positions,
    seed_from_scan,
    subset_beams,
)
from localization.core.geometry import compose, wrap_angle
from localization.core.localizer import Localizer
from localization.core.models.beam import BeamModel
from localization.core.occupancy_map import OccupancyMap, load_map
from localization.core.parameters import ParameterError, Parameters
from localization.core.raycast import ExactRayCaster
from localization.sim import simulate


def room_map() -> OccupancyMap:
    """A 4 m x 3 m room with a box in one corner and a pillar: no symmetry."""
    data = np.full((64, 84), -1, dtype=np.int8)
    data[2:62, 2:82] = 0
    data[1, 1:83] = data[62, 1:83] = 100
    data[1:63, 1] = data[1:63, 82] = 100
    data[40:62, 60:82] = 100  # the box
    data[20:24, 20:24] = 100  # the pillar
    return OccupancyMap(data, 0.05, (0.0, 0.0, 0.0))


def test_lattice_and_beam_subset():
    m = room_map()
    xy = lattice_positions(m, 0.2, np.random.default_rng(0))
    assert len(xy) > 50 and m.is_free(xy).all()
    d = np.abs(np.diff(np.unique(np.round(xy[:, 0], 6))))
    assert np.allclose(d, 0.2)  # every 4th cell
    r = np.array([1.0, np.inf, 2.0, np.nan, 3.0, 4.0])
    z, a = subset_beams(r, np.arange(6.0), 3)
    assert np.isfinite(z).all() and list(a) == [0.0, 4.0, 5.0]


def test_lattice_poses_in_chunks_are_the_indexed_poses():
    """Pose i of the lattice is position i // H with heading i % H, for chunks cut anywhere."""
    rng = np.random.default_rng(3)
    xy, theta = rng.uniform(-5.0, 5.0, (23, 2)), rng.uniform(-np.pi, np.pi, 7)
    total = len(xy) * len(theta)
    for start, count in [(0, total), (0, 1), (5, 9), (6, 7), (7, 14), (100, total - 100), (total - 1, 1)]:
        idx = np.arange(start, start + count)
        got = lattice_poses(xy, theta, start, count)
        assert got.flags.c_contiguous and got.shape == (count, 3)
        np.testing.assert_array_equal(got, np.column_stack([xy[idx // 7], theta[idx % 7]]))


@pytest.mark.parametrize("model_name", ["beam", "likelihood_field"])
def test_seeds_concentrate_at_the_true_pose_and_keep_a_uniform_share(model_name):
    """Any model of the SensorModel protocol scores the lattice (the beam model, the likelihood field)."""
    m = room_map()
    if model_name == "beam":
        model = BeamModel(ray_caster="exact", laser_offset=(0.0, 0.0, 0.0))
    else:
        from localization.core.models.likelihood_field import LikelihoodFieldModel
        model = LikelihoodFieldModel(laser_offset=(0.0, 0.0, 0.0))
    model.set_map(m)
    true = np.array([1.13, 1.71, 0.4])
    angles = np.linspace(-2.356, 2.356, 100)
    ranges = ExactRayCaster(m, model.max_range).cast(true[None], angles)[0]
    params = ScanSeedParams(global_seed_step=0.2, global_seed_headings=36, global_seed_beams=40,
                            global_seed_candidates=50, global_seed_temperature=4.0, global_seed_uniform=0.2)
    res = seed_from_scan(m, model, ranges, angles, 2000, np.random.default_rng(1), params)
    assert res.poses.shape == (2000, 3) and np.isfinite(res.poses).all()
    assert m.is_free(res.poses[:, :2]).all()
    best = res.candidates[0]
    assert np.hypot(*(best[:2] - true[:2])) <= 0.2 and abs(wrap_angle(best[2] - true[2])) <= np.pi / 36 + 1e-9
    assert np.all(np.diff(res.candidate_log_likelihood) <= 0)  # best first
    near = (np.hypot(*(res.poses[:, :2] - true[:2]).T) < 0.3) & (np.abs(wrap_angle(res.poses[:, 2] - true[2])) < 0.2)
    assert near[:1600].mean() > 0.3  # the seeded share piles up at the truth ...
    assert near[1600:].mean() < 0.05  # ... the last 20 % are the uniform share
    assert res.lattice_poses == len(lattice_positions(m, 0.2, np.random.default_rng(1))) * 36


def test_global_init_is_a_checked_parameter():
    assert Parameters().global_init == "scan"
    with pytest.raises(ParameterError):
        Parameters(global_init="magic")


@pytest.mark.parametrize("method", ["scan", "uniform"])
def test_first_scan_seeds_only_with_global_init_scan(method, monkeypatch):
    import localization.core.localizer.seeder as L
    calls = []
    monkeypatch.setattr(L, "seed_from_scan", lambda *a, **k: calls.append(1) or seed_from_scan(*a, **k))
    m = room_map()
    loc = Localizer(Parameters(global_init=method, global_num_particles=3000, random_seed=3, ray_caster="exact",
                               laser_offset_x=0.0, global_seed_candidates=100))
    loc.set_map(m)
    loc.initialize_global(0.0)
    true = np.array([2.0, 1.0, -1.2])
    angles = np.linspace(-2.356, 2.356, 1081)
    ranges = ExactRayCaster(m, 10.0).cast(true[None], angles)[0]
    from localization.core.scan import ScanData
    est = loc.on_scan(ScanData(0.0, ranges, angles[0], angles[-1], angles[1] - angles[0], 0.02, 10.0)).estimate
    assert est is not None
    err = np.hypot(*(est.pose[:2] - true[:2]))
    assert len(calls) == (1 if method == "scan" else 0)
    if method == "scan":
        assert err < 0.3 and not loc.global_mode  # one scan of an asymmetric room suffices
    loc.on_scan(ScanData(0.1, ranges, angles[0], angles[-1], angles[1] - angles[0], 0.02, 10.0))
    assert len(calls) == (1 if method == "scan" else 0)  # once per global spread, not per scan


def test_global_localization_in_the_long_corridor_within_seconds():
    """The robustness benchmark's start 4 (the long self-similar corridor; 16 s with the plain
    uniform spread): below 0.3 m for good within 5 s of driving."""
    stata = load_map("stata_basement")
    start = int(4 * len(RB.loop_path()) / 10) + 37
    rec = simulate(RB.loop_config(start, 6.0, seed=104), stata)
    loc = Localizer(Parameters(ray_caster="lookup_table", random_seed=104, global_num_particles=20000),
                    logging.getLogger("test.global"))
    loc.set_map(stata)
    run = RB.run_recording(rec, loc, init="global")
    t = RB.settle_time(RB.ct_errors(rec, run), float(rec.odometry.t[0]))
    assert t is not None and t <= 5.0
    assert not loc.global_mode and loc.num_particles == loc.params.num_particles
    assert run.recoveries == 0
    laser = compose(run.est_poses[-1], loc.laser_offset)
    assert stata.is_free(laser[None, :2])[0]


def test_the_lattice_is_scored_with_the_scans_range_max():
    """seed_from_scan scores as a sensor update does: z_max from the scan's range_max (laser_max_range <= 0)."""
    from localization.core.models.likelihood_field import LikelihoodFieldModel
    m = room_map()
    model = LikelihoodFieldModel(laser_offset=(0.0, 0.0, 0.0), laser_max_range=-1.0, occupancy_map=m)
    true = np.array([1.13, 1.71, 0.4])
    angles = np.linspace(-2.356, 2.356, 100)
    ranges = ExactRayCaster(m, 10.0).cast(true[None], angles)[0]
    params = ScanSeedParams(global_seed_step=0.2, global_seed_headings=12, global_seed_beams=40,
                            global_seed_candidates=20, global_seed_temperature=4.0, global_seed_uniform=0.2)
    seeds = {r: seed_from_scan(m, model, ranges, angles, 100, np.random.default_rng(1), params, range_max=r)
             for r in (1.5, 8.0)}
    best = seeds[8.0].candidates[0]
    z, a = subset_beams(ranges, angles, 40)
    for r, res in seeds.items():
        want = model.log_likelihood(res.candidates[:1], z, a, range_max=r)[0]
        assert res.candidate_log_likelihood[0] == pytest.approx(want)
    assert seeds[1.5].candidate_log_likelihood[0] != pytest.approx(seeds[8.0].candidate_log_likelihood[0])
    assert np.hypot(*(best[:2] - true[:2])) <= 0.3
