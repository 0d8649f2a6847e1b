"""KLD-adaptive particle count: the bound against hand values, its limits, binning, and the
filter's cloud shrinking when tight and growing when spread."""
from __future__ import annotations

from dataclasses import fields

import numpy as np
import pytest
from helpers import corridor_map

from localization.core.filter.kld import KLDParams, KLDSampler, bin_keys, count_bins, kld_sample_size
from localization.core.localizer import Localizer, build_filter
from localization.core.parameters import BY_NAME, Parameters


def test_the_bound_against_hand_values():
    # n = (k-1)/(2 eps) (1 - 2/(9(k-1)) + sqrt(2/(9(k-1))) z)^3, computed by hand: 19.27, 6732.45, 10432.22
    assert kld_sample_size(2, 0.05, 0.99, 1, 100000) == 20
    assert kld_sample_size(100, 0.01, 2.326, 1, 100000) == 6733
    assert kld_sample_size(1000, 0.05, 0.99, 1, 100000) == 10433
    assert list(kld_sample_size(np.array([2, 100]), 0.01, 2.326, 1, 100000)) == [kld_sample_size(2, 0.01, 2.326, 1,
                                                                                                  100000), 6733]


def test_the_bound_respects_min_and_max_and_grows_with_k():
    assert kld_sample_size(1, 0.05, 0.99, 500, 5000) == 500  # one bin: Fox's bound is 0 -> min
    assert kld_sample_size(0, 0.05, 0.99, 500, 5000) == 500
    assert kld_sample_size(2, 0.05, 0.99, 500, 5000) == 500
    assert kld_sample_size(10 ** 6, 0.05, 0.99, 500, 5000) == 5000
    n = kld_sample_size(np.arange(1, 3000), 0.05, 0.99, 1, 10 ** 7)
    assert np.all(np.diff(n) >= 0)
    with pytest.raises(ValueError):
        KLDSampler(min_particles=10, max_particles=5)


def test_bins_of_half_a_metre_and_ten_degrees():
    p = np.array([[0.1, 0.1, 0.0], [0.4, 0.4, 0.1], [0.6, 0.1, 0.0], [0.1, -0.1, 0.0], [0.1, 0.1, 0.2],
                  [0.1, 0.1, np.pi], [0.1, 0.1, -np.pi]])  # +pi and -pi: the same heading, the same bin
    keys = bin_keys(p, 0.5, np.radians(10))
    assert keys[0] == keys[1] and len({keys[0], keys[2], keys[3], keys[4]}) == 4 and keys[5] == keys[6]
    assert count_bins(p, 0.5, np.radians(10)) == 5


def test_params_defaults_come_from_the_table():
    for f in fields(KLDParams):
        assert f.default == BY_NAME[f.name].default, f.name
    assert Parameters().adaptive_particles is False and build_filter(Parameters()).kld is None
    pf = build_filter(Parameters(adaptive_particles=True, min_particles=100, max_particles=3000))
    assert pf.kld is not None and pf.kld.params.max_particles == 3000


def _sampler():
    return KLDSampler(min_particles=200, max_particles=20000, pf_err=0.05, pf_z=0.99)


def test_a_tight_cloud_shrinks_to_min_and_a_spread_one_grows():
    rng = np.random.default_rng(0)
    tight = np.array([1.2, 3.3, 0.4]) + rng.normal(0, [0.05, 0.05, 0.02], (5000, 3))
    w = np.full(5000, 1 / 5000)
    draw = _sampler().resample(tight, w, rng)
    assert draw.indices.size == 200 and draw.bins <= 8
    spread = np.column_stack([rng.uniform(0, 40, 5000), rng.uniform(0, 20, 5000), rng.uniform(-np.pi, np.pi, 5000)])
    draw = _sampler().resample(spread, w, rng)
    assert draw.indices.size == 20000  # thousands of bins: the bound exceeds max
    medium = np.column_stack([rng.uniform(0, 5, 5000), rng.uniform(0, 1, 5000), rng.normal(0, 0.2, 5000)])
    draw = _sampler().resample(medium, w, rng)
    k = draw.bins
    assert 200 < draw.indices.size < 20000
    assert draw.indices.size == kld_sample_size(k, 0.05, 0.99, 200, 20000)  # stopped exactly at the bound
    assert k <= count_bins(medium, 0.5, np.radians(10))


def test_resampling_follows_the_weights():
    rng = np.random.default_rng(1)
    cloud = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    draw = _sampler().resample(cloud, np.array([0.9, 0.1]), rng)
    share = np.mean(draw.indices == 0)
    assert draw.indices.size == 200 and abs(share - 0.9) < 0.05


def test_the_filter_shrinks_when_tight_and_grows_when_spread():
    m = corridor_map(width_cells=400)
    params = Parameters(adaptive_particles=True, min_particles=300, max_particles=8000, num_particles=2000,
                        random_seed=0, recovery=False, global_init="uniform")
    loc = Localizer(params)
    loc.set_map(m)
    pf = loc._pf
    loc.set_initial_pose([5.0, 1.5, 0.0])
    pf.initialize_gaussian([5.0, 1.5, 0.0], std=(0.05, 0.05, 0.02))
    pf.resample()
    assert pf.num_particles == 300 and pf.particles.shape == (300, 3) and pf.log_weights.shape == (300,)
    pf.initialize_uniform(m)  # spread over the corridor (20 m x 2 m, all headings): hundreds of bins
    pf.resample()
    assert pf.num_particles > 3000 and pf.particles.shape == (pf.num_particles, 3)
    # global localization and recovery start at max_particles
    loc.initialize_global()
    assert pf.num_particles == 8000 and loc._pipeline.seeder.count == 8000
    # ... and keep it until the spread converges (KLD on a peaked first scan would drop it to the minimum)
    assert pf.kld_hold
    pf.resample(np.r_[1.0, np.zeros(pf.num_particles - 1)])
    assert pf.num_particles == 8000
    loc.set_initial_pose([5.0, 1.5, 0.0])
    assert not pf.kld_hold and pf.num_particles == 2000


def test_the_feed_log_records_the_particle_count_per_sensor_update():
    from localization.core.geometry import compose
    from localization.core.odometry import TwistData
    from localization.core.raycast.exact import ExactRayCaster
    from localization.core.scan import ScanData
    from localization.eval.feed import Feeder

    m = corridor_map(width_cells=400)
    loc = Localizer(Parameters(adaptive_particles=True, min_particles=200, max_particles=4000, num_particles=3000,
                               random_seed=1, recovery=False, sensor_model="likelihood_field",
                               laser_max_range=8.0))
    loc.set_map(m)
    truth = np.array([5.0, 1.5, 0.0])
    loc.set_initial_pose(truth, np.diag([0.3, 0.3, 0.1]) ** 2)
    caster = ExactRayCaster(m, 8.0)
    angles = np.linspace(-2.35, 2.35, 181)
    feeder = Feeder(loc)
    for i in range(8):
        t = 0.1 * i
        pose = truth + [0.1 * i, 0.0, 0.0]
        feeder.odometry(TwistData(t, 1.0, 0.0, 0.0))
        ranges = caster.cast(compose(pose[None], np.array([0.275, 0.0, 0.0])), angles)[0]
        feeder.scan(ScanData(t, ranges, angles[0], angles[-1], angles[1] - angles[0], 0.02, 8.0))
    log = feeder.log
    assert len(log.particles) == log.counts["sensor_updates"] >= 5 and len(log.particles_t) == len(log.particles)
    assert log.particles[0] < 3000 and min(log.particles) >= 200  # the spread start shrinks as the cloud tightens
