"""The particle filter core and the message-level localizer (no ROS)."""
import numpy as np
import pytest

from localization.core.filter.mcl import MonteCarloLocalizer
from localization.core.geometry import compose, integrate_twist
from localization.core.localizer import Localizer
from localization.core.models.beam import BeamModel as SensorModel
from localization.core.models.motion import MotionModel
from localization.core.occupancy_map import OccupancyMap
from localization.core.odometry import TwistData
from localization.core.parameters import ParameterError, Parameters
from localization.core.paths import config_dir
from localization.core.raycast.exact import ExactRayCaster
from localization.core.scan import ScanData


@pytest.fixture(scope="module")
def stata(maps_dir):
    return OccupancyMap.from_yaml(maps_dir / "stata_basement.yaml")


def test_estimate_is_weighted_and_circular():
    f = MonteCarloLocalizer(MotionModel(), SensorModel(), num_particles=4, rng=0)
    f.particles = np.array([[0.0, 0.0, np.pi - 0.1], [2.0, 0.0, -np.pi + 0.1], [0.0, 2.0, np.pi], [9.0, 9.0, 0.0]])
    f.log_weights = np.log(np.array([1.0, 1.0, 2.0, 1e-300]))
    est = f.estimate()
    assert est.pose[0] == pytest.approx(0.5) and est.pose[1] == pytest.approx(1.0)
    assert abs(abs(est.pose[2]) - np.pi) < 1e-6
    assert est.covariance.shape == (3, 3) and np.allclose(est.covariance, est.covariance.T)
    assert est.covariance[2, 2] < 0.01  # theta differences wrapped, not ~(2 pi)^2


def test_systematic_resampling_follows_weights():
    f = MonteCarloLocalizer(MotionModel(), SensorModel(), num_particles=1000, roughening=(0, 0, 0), rng=1)
    f.particles = np.column_stack([np.arange(1000.0), np.zeros(1000), np.zeros(1000)])
    w = np.zeros(1000)
    w[[10, 20]] = [0.75, 0.25]
    f.resample(w)
    vals, counts = np.unique(f.particles[:, 0], return_counts=True)
    assert vals.tolist() == [10.0, 20.0] and counts.tolist() == [750, 250]
    assert np.allclose(f.weights, 1e-3)


def test_initialisation_gaussian_and_uniform(stata):
    f = MonteCarloLocalizer(MotionModel(), SensorModel(), num_particles=20000, rng=2)
    f.initialize_gaussian([1.0, 2.0, 3.0], std=(0.5, 0.5, 0.2))
    assert np.std(f.particles[:, 0]) == pytest.approx(0.5, rel=0.05)
    assert np.all(np.abs(f.particles[:, 2]) <= np.pi)
    cov = np.diag([0.04, 0.09, 0.01])
    f.initialize_gaussian([1.0, 2.0, 0.0], covariance=cov)
    assert np.allclose(np.cov(f.particles.T), cov, atol=0.01)
    f.initialize_uniform(stata)
    assert stata.is_free(f.particles[:, :2]).mean() > 0.97
    assert np.ptp(f.particles[:, 0]) > 50


def test_all_zero_likelihood_is_reported_and_weights_kept(stata):
    f = MonteCarloLocalizer(MotionModel(), SensorModel(occupancy_map=stata), num_particles=50, rng=3)
    f.initialize_gaussian([500.0, 500.0, 0.0], std=(0.1, 0.1, 0.1))  # far off the map
    before = f.log_weights.copy()
    result = f.sensor_update(np.full(10, 1.0), np.linspace(-2, 2, 10))
    assert not result.ok and np.array_equal(f.log_weights, before)
    assert not np.any(np.isnan(f.estimate().pose))


def test_twist_to_delta_arc():
    d = integrate_twist(2.0, 0.0, 0.0, 0.5)
    assert np.allclose(d, [1.0, 0.0, 0.0])
    d = integrate_twist(1.0, 0.0, np.pi, 1.0)  # half circle of radius 1/pi
    assert np.allclose(d, [0.0, 2.0 / np.pi, np.pi], atol=1e-12)
    small = integrate_twist(1.0, 0.0, 1e-9, 1.0)
    assert np.allclose(small, [1.0, 0.0, 1e-9])


def drive(loc, m, truth, seconds, speed=2.0, rng=None, odom_noise=0.0):
    """Synthetic straight drive: 50 Hz odometry, 40 Hz scans from the exact caster."""
    caster = ExactRayCaster(m, 10.0)
    angles = np.linspace(-2.356, 2.356, 1081)
    rng = rng or np.random.default_rng(0)
    errors = []
    t, next_scan = 0.0, 0.0
    loc.on_odometry(TwistData(t, 0.0, 0.0, 0.0))
    while t < seconds:
        t = round(t + 0.02, 6)
        truth = compose(truth, [speed * 0.02, 0.0, 0.0])
        noise = rng.normal(0, odom_noise, 3)
        loc.on_odometry(TwistData(t, speed + noise[0], noise[1], noise[2]))
        if t >= next_scan:
            next_scan += 0.025
            r = caster.cast(compose(truth, [0.275, 0, 0])[None], angles)[0] + rng.normal(0, 0.01, angles.size)
            est = loc.on_scan(ScanData(t, r, -2.356, 2.356, angles[1] - angles[0], 0.02, 10.0)).estimate
            if est is not None:
                errors.append(np.hypot(*(est.pose[:2] - truth[:2])))
    return truth, np.array(errors)


def test_localizer_converges_on_a_corridor_drive(stata):
    loc = Localizer(Parameters(num_particles=800, random_seed=4))
    loc.set_map(stata)
    start = np.array([-6.0, 20.0, -2.24])
    loc.set_initial_pose(start + [0.4, -0.3, 0.15])
    _, errors = drive(loc, stata, start, 2.5, odom_noise=0.3)
    assert errors.size > 50
    assert errors[-20:].mean() < 0.1, errors[::10]


def test_localizer_waits_for_map_and_pose_and_is_seeded(stata):
    loc = Localizer(Parameters(num_particles=200, random_seed=5))
    assert loc.on_odometry(TwistData(0.0, 1.0, 0.0, 0.0)) is None
    assert loc.on_scan(ScanData(0.0, np.ones(10), -1, 1, 0.2, 0.0, 10.0)).estimate is None
    loc.set_map(stata)
    assert not loc.ready and loc.on_scan(ScanData(0.0, np.ones(10), -1, 1, 0.2, 0.0, 10.0)).estimate is None
    runs = []
    for _ in range(2):
        loc = Localizer(Parameters(num_particles=200, random_seed=5))
        loc.set_map(stata)
        loc.set_initial_pose([-6.0, 20.0, -2.24])
        _, errors = drive(loc, stata, np.array([-6.0, 20.0, -2.24]), 0.5, odom_noise=0.3)
        runs.append((loc.estimate.pose.copy(), errors))
    assert np.array_equal(runs[0][0], runs[1][0]) and np.array_equal(runs[0][1], runs[1][1])


def test_odometry_stamp_going_backwards_does_not_move_particles(stata):
    loc = Localizer(Parameters(num_particles=100, random_seed=6))
    loc.set_map(stata)
    loc.set_initial_pose([-6.0, 20.0, -2.24])
    before = loc.on_odometry(TwistData(10.0, 0.0, 0.0, 0.0)).pose
    particles = loc.particles()
    assert loc.on_odometry(TwistData(9.0, 3.0, 0.0, 0.0)) is None  # backwards: reference reset
    assert np.array_equal(loc.particles(), particles) and np.array_equal(loc.estimate.pose, before)
    after = loc.on_odometry(TwistData(9.02, 1.0, 0.0, 0.0))  # a new history from 9.0: 0.02 s at 1 m/s
    assert np.hypot(*(after.pose[:2] - before[:2])) == pytest.approx(0.02, abs=1e-9)


def test_parameters_validation_and_config_files():
    with pytest.raises(ParameterError, match="num_particles"):
        Parameters(num_particles=0)
    with pytest.raises(ParameterError, match="unknown"):
        Parameters(not_a_parameter=1)
    with pytest.raises(ParameterError, match="squash_factor"):
        Parameters(squash_factor=-1.0)
    assert Parameters(num_particles=10).num_particles == 10
    for name in ("params.yaml", "real_params.yaml"):
        p = Parameters.from_yaml(config_dir() / name)
        assert p.num_particles >= 1
