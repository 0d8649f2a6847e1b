"""The tempered first update after an initial pose (``MonteCarloLocalizer.sensor_update`` with ``stages`` > 1).

A Gaussian likelihood over a Gaussian initial cloud has a closed-form posterior and evidence:
the tempered stages must land on them, where one plain update leaves the estimate on the few
initial particles nearest to the likelihood's peak.
"""
import numpy as np
import pytest

from localization.core.filter.mcl import MonteCarloLocalizer, _tempering_step, effective_sample_size
from localization.core.localizer import Localizer
from localization.core.models.motion import MotionModel
from localization.core.occupancy_map import OccupancyMap
from localization.core.odometry import TwistData
from localization.core.parameters import Parameters
from localization.core.raycast.exact import ExactRayCaster
from localization.core.scan import ScanData

PRIOR_MEAN = np.array([1.0, 2.0, 0.3])
PRIOR_STD = np.array([0.5, 0.5, 0.2])
PEAK = np.array([1.3, 1.8, 0.4])  # where the "scan" points
SIGMA = np.array([0.02, 0.02, 0.01])  # its likelihood's std per axis


class GaussianScanModel:
    """log p(z | x) = -½ Σ ((x − PEAK) / SIGMA)² (θ wrapped): a scan whose posterior is known."""
    last_beams_used = 3

    def log_likelihood(self, particles, ranges, angles, offsets=None, range_max=None):
        d = particles - PEAK
        d[:, 2] = (d[:, 2] + np.pi) % (2 * np.pi) - np.pi
        return -0.5 * np.sum((d / SIGMA) ** 2, axis=1)


def posterior():
    """Mean and std of the Gaussian prior × Gaussian likelihood, per axis."""
    precision = 1 / PRIOR_STD ** 2 + 1 / SIGMA ** 2
    mean = (PRIOR_MEAN / PRIOR_STD ** 2 + PEAK / SIGMA ** 2) / precision
    return mean, 1 / np.sqrt(precision)


def log_evidence():
    """log ∫ N(x; PRIOR_MEAN, PRIOR_STD²) exp(-½ ((x − PEAK)/SIGMA)²) dx (per axis, summed)."""
    var = PRIOR_STD ** 2 + SIGMA ** 2
    return float(np.sum(np.log(SIGMA / np.sqrt(var)) - 0.5 * (PEAK - PRIOR_MEAN) ** 2 / var))


def cloud(seed, n=2000):
    f = MonteCarloLocalizer(MotionModel(), GaussianScanModel(), num_particles=n, rng=seed)
    f.initialize_gaussian(PRIOR_MEAN, std=PRIOR_STD)
    return f


def test_tempered_update_lands_on_the_posterior_where_a_plain_update_does_not():
    mean, std = posterior()
    plain, tempered = [], []
    for seed in range(8):
        f = cloud(seed)
        assert f.sensor_update(None, None).ok
        plain.append(np.abs(f.estimate().pose - mean) / std)
        f = cloud(seed)
        result = f.sensor_update(None, None, stages=8)
        assert result.ok and result.resampled
        est = f.estimate()
        tempered.append(np.abs(est.pose - mean) / std)
        spread = np.sqrt(np.diag(est.covariance))
        # the jitter between stages neither collapses the cloud nor leaves it wide: the posterior's std
        assert np.all(spread > 0.6 * std) and np.all(spread < 1.6 * std), (spread, std)
    plain, tempered = np.array(plain), np.array(tempered)
    # the posterior's std is ~2 cm, the initial cloud's 0.5 m: one update leaves the mean off by
    # several posterior stds, the stages bring it within one
    assert np.median(tempered) < 0.7, tempered
    assert np.median(plain) > 2.0 * np.median(tempered), (np.median(plain), np.median(tempered))


def test_tempered_update_counts_the_scan_once():
    """The stages' log normalisers sum to the scan's evidence, as one exact update would give it (the
    jitter widens each stage's cloud by (1 + h²): a little below it)."""
    evidences = [cloud(seed, 5000).sensor_update(None, None, stages=8).mean_log_likelihood
                 for seed in range(4)]
    assert np.median(evidences) == pytest.approx(log_evidence(), abs=0.8)
    # a scan applied twice (β summing to 2) would give a clearly smaller evidence and a narrower cloud
    f = cloud(0, 5000)
    f.sensor_update(None, None, stages=8)
    once = np.sqrt(np.diag(f.estimate().covariance))
    f.sensor_update(None, None, stages=8)
    assert np.all(np.sqrt(np.diag(f.estimate().covariance)) < 0.85 * once)


def test_one_stage_is_the_plain_update():
    a, b = cloud(3), cloud(3)
    ra, rb = a.sensor_update(None, None), b.sensor_update(None, None, stages=1)
    assert ra == rb and np.array_equal(a.particles, b.particles)


def test_tempering_step_keeps_half_the_cloud_effective():
    rng = np.random.default_rng(0)
    log_w = np.full(1000, -np.log(1000))
    log_lik = -0.5 * (rng.standard_normal(1000) * 30) ** 2
    possible = np.ones(1000, bool)
    beta = _tempering_step(log_w, log_lik, possible, 1.0, 500.0)
    assert 0 < beta < 1
    assert effective_sample_size(log_w + beta * log_lik) == pytest.approx(500, rel=0.01)
    flat = np.zeros(1000)  # a scan that tells nothing: one stage takes all of it
    assert _tempering_step(log_w, flat, possible, 0.7, 500.0) == 0.7


def test_impossible_scan_is_reported_and_the_cloud_kept():
    class Impossible(GaussianScanModel):
        def log_likelihood(self, particles, *args, **kwargs):
            return np.full(len(particles), -np.inf)
    f = MonteCarloLocalizer(MotionModel(), Impossible(), num_particles=100, rng=1)
    f.initialize_gaussian(PRIOR_MEAN, std=PRIOR_STD)
    before = f.particles.copy()
    result = f.sensor_update(None, None, stages=8)
    assert not result.ok and np.array_equal(f.particles, before)
    assert np.all(np.isfinite(f.estimate().pose))


def test_a_later_stage_where_every_particle_is_impossible_keeps_the_stages_so_far():
    class Vanishing(GaussianScanModel):
        calls = 0

        def log_likelihood(self, particles, *args, **kwargs):
            Vanishing.calls += 1
            ll = super().log_likelihood(particles, *args, **kwargs)
            return ll if Vanishing.calls == 1 else np.full(len(particles), -np.inf)
    f = MonteCarloLocalizer(MotionModel(), Vanishing(), num_particles=500, rng=4)
    f.initialize_gaussian(PRIOR_MEAN, std=PRIOR_STD)
    result = f.sensor_update(None, None, stages=8)
    assert result.ok and Vanishing.calls == 2 and np.isfinite(result.mean_log_likelihood)
    assert np.all(np.isfinite(f.log_weights)) and np.all(np.isfinite(f.estimate().pose))
    # the first stage moved the cloud toward the peak
    assert np.hypot(*(f.estimate().pose[:2] - PEAK[:2])) < np.hypot(*(PRIOR_MEAN[:2] - PEAK[:2]))


def test_partly_impossible_cloud_keeps_only_possible_particles():
    class HalfPlane(GaussianScanModel):
        def log_likelihood(self, particles, *args, **kwargs):
            ll = super().log_likelihood(particles, *args, **kwargs)
            return np.where(particles[:, 0] < 1.0, -np.inf, ll)  # x < 1 m: inside a wall
    f = MonteCarloLocalizer(MotionModel(), HalfPlane(), num_particles=2000, rng=2)
    f.initialize_gaussian(PRIOR_MEAN, std=PRIOR_STD)
    assert f.sensor_update(None, None, stages=8).ok
    assert np.all(np.isfinite(f.particles)) and np.all(np.isfinite(f.log_weights))
    assert abs(f.estimate().pose[0] - posterior()[0][0]) < 0.03


def stationary_scan(m, pose, t):
    angles = np.linspace(-2.356, 2.356, 1081)
    r = ExactRayCaster(m, 10.0).cast(np.array([pose]), angles)[0]
    return ScanData(t, r, -2.356, 2.356, angles[1] - angles[0], 0.0, 10.0)


def test_localizer_tempers_only_the_first_update_after_an_initial_pose(maps_dir):
    """A standing robot, an initial pose 0.3 m off: the first estimate (the only update while it
    stands) is the scan's posterior mean, the same within 1 cm on every seed with the stages; one
    plain update scatters it by several cm over the seeds."""
    m = OccupancyMap.from_yaml(maps_dir / "stata_basement.yaml")
    truth = np.array([-6.0, 20.0, -2.24])
    first = {1: [], 8: []}
    for stages, seed in [(s, seed) for s in first for seed in range(6)]:
        loc = Localizer(Parameters(num_particles=1000, random_seed=seed, initial_update_stages=stages,
                                   laser_offset_x=0.0))
        loc.set_map(m)
        loc.on_odometry(TwistData(0.0, 0.0, 0.0, 0.0))
        loc.set_initial_pose(truth + [0.2, -0.2, 0.1], stamp=0.0)
        assert loc._pipeline.temper_next
        est = loc.on_scan(stationary_scan(m, truth, 0.0)).estimate
        assert est is not None and not loc._pipeline.temper_next  # used once
        first[stages].append(est.pose[:2] - truth[:2])
        loc.initialize_global(0.0)
        assert not loc._pipeline.temper_next  # a global spread has its own seeding, no stages
    plain, tempered = np.array(first[1]), np.array(first[8])
    assert np.all(np.hypot(*tempered.T) < 0.05), tempered
    assert np.all(tempered.std(axis=0) < 0.01), tempered
    assert np.all(plain.std(axis=0) > 2 * tempered.std(axis=0)), (plain, tempered)
