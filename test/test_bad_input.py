"""Bad input reaching the localizer: a clear log line, no crash, no NaN, state kept sane."""
import logging

import numpy as np
import pytest
from helpers import corridor_map
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from localization.core.localizer import Localizer
from localization.core.occupancy_map import MapError, OccupancyMap
from localization.core.odometry import TwistData
from localization.core.parameters import Parameters
from localization.core.scan import ScanData

FLOATS = st.floats(allow_nan=True, allow_infinity=True, width=64)


@pytest.fixture()
def loc():
    loc = Localizer(Parameters(num_particles=200, random_seed=1, ray_caster="distance_transform"))
    loc.set_map(corridor_map())
    loc.set_initial_pose([5.0, 1.5, 0.0])
    return loc


def good_scan(n=200):
    return np.full(n, 1.0), -2.0, 2.0, 4.0 / (n - 1), 0.02, 10.0


def assert_sane(loc):
    assert np.all(np.isfinite(loc.particles()))
    est = loc.estimate
    assert est is not None and np.all(np.isfinite(est.pose)) and np.all(np.isfinite(est.covariance))


@pytest.mark.parametrize("ranges", [
    np.full(200, np.nan), np.full(200, np.inf), np.full(200, -np.inf), np.full(200, -1.0), np.zeros(200),
    np.full(200, 1e300), np.array([]), np.r_[np.full(100, np.nan), np.full(100, 1.0)],
])
def test_broken_scans(loc, ranges, caplog):
    _, a0, a1, inc, rmin, rmax = good_scan(max(len(ranges), 2))
    with caplog.at_level(logging.INFO):
        loc.on_odometry(TwistData(0.0, 0.0, 0.0, 0.0))
        loc.on_odometry(TwistData(0.02, 1.0, 0.0, 0.0))
        loc.on_scan(ScanData(0.02, ranges, a0, a1, inc, rmin, rmax))
    assert_sane(loc)


def test_all_invalid_and_empty_scans_say_so(loc, caplog):
    with caplog.at_level(logging.WARNING):
        loc.on_scan(ScanData(0.0, np.full(50, np.nan), -2.0, 2.0, 0.08, 0.02, 10.0))
        loc.on_scan(ScanData(0.0, np.array([]), -2.0, 2.0, 0.08, 0.02, 10.0))
    assert "no valid range" in caplog.text and "no ranges" in caplog.text


@pytest.mark.parametrize("angles", [(2.0, -2.0, -0.02), (-2.0, 2.0, 0.0), (np.nan, 2.0, 0.02), (-2.0, 2.0, np.inf)])
def test_reversed_or_broken_angles(loc, angles):
    ranges = np.full(201, 1.0)
    loc.on_scan(ScanData(0.0, ranges, *angles, 0.02, 10.0))
    assert_sane(loc)


def test_odometry_nan_absurd_and_backwards(loc, caplog):
    loc.on_odometry(TwistData(1.0, 0.0, 0.0, 0.0))
    before = loc.particles()
    with caplog.at_level(logging.WARNING):
        assert loc.on_odometry(TwistData(1.02, np.nan, 0.0, 0.0)) is None
        assert loc.on_odometry(TwistData(1.04, 500.0, 0.0, 0.0)) is None
        assert loc.on_odometry(TwistData(0.5, 1.0, 0.0, 0.0)) is None  # backwards (bag loop)
        assert loc.on_odometry(TwistData(30.0, 1.0, 0.0, 0.0)) is None  # gap of many seconds
    assert np.array_equal(loc.particles(), before)
    assert "non-finite" in caplog.text and "absurd" in caplog.text and "jumped" in caplog.text
    assert loc.on_odometry(TwistData(30.02, 1.0, 0.0, 0.0)) is not None
    assert_sane(loc)


def test_initial_pose_nan_outside_and_in_wall(caplog):
    loc = Localizer(Parameters(num_particles=100, random_seed=2, ray_caster="distance_transform"))
    m = corridor_map()
    loc.set_map(m)
    with caplog.at_level(logging.WARNING):
        assert loc.set_initial_pose([np.nan, 1.0, 0.0]) is False
        assert not loc.ready
        assert loc.set_initial_pose([50.0, 50.0, 0.0])  # far outside the map
        assert m.is_free(loc.estimate.pose[None, :2])[0] or np.linalg.norm(loc.estimate.pose[:2] - [9.9, 2.45]) < 1
        assert loc.set_initial_pose([5.0, 0.52, 0.0])  # inside the wall row
        assert abs(loc.estimate.pose[1] - 0.575) < 0.3
    assert "not finite" in caplog.text and "nearest free cell" in caplog.text


@pytest.mark.parametrize("variance", [np.nan, np.inf, 0.0, 8.98846567e307, 1e5])
def test_initial_pose_covariance_that_is_not_a_spread_falls_back_to_the_default(variance, caplog):
    """A /initialpose covariance that is non-finite, zero or absurdly large (found by the node fuzz
    test: 9e307 sampled NaN particles) gives one warning and the initial_std_* spread."""
    loc = Localizer(Parameters(num_particles=100, random_seed=2, ray_caster="distance_transform"))
    loc.set_map(corridor_map())
    cov = np.zeros((3, 3))
    cov[0, 0] = cov[2, 2] = variance
    with caplog.at_level(logging.WARNING):
        assert loc.set_initial_pose([5.0, 1.5, 0.0], cov)
    assert "not a usable spread" in caplog.text
    assert_sane(loc)
    assert np.abs(loc.particles()[:, 0] - 5.0).max() < 10 * loc.params.initial_std_xy


def test_maps_without_free_space_are_rejected_and_old_map_kept(loc):
    old = loc.map
    for value in (-1, 100):
        with pytest.raises(MapError):
            loc.set_map(OccupancyMap(np.full((20, 20), value, dtype=np.int8), 0.05))
    assert loc.map is old and loc.ready


def test_new_map_of_another_size_while_running(loc):
    loc.set_map(corridor_map(width_cells=400, height_cells=100, wall_rows=(20, 80)))
    loc.on_scan(ScanData(0.0, *good_scan()))
    assert_sane(loc)
    # a map where no particle is valid any more: the filter waits for a new pose instead of guessing
    loc.set_map(corridor_map(origin=(100.0, 100.0, 0.0)))
    assert not loc.ready and loc.estimate is None


def test_an_initial_pose_sent_while_a_new_map_is_prepared_is_a_pose_in_that_map(loc, caplog):
    """/map then /initialpose: the pose waits for the map being prepared (on the old map it could lie
    in a wall and be moved, or the cloud would start in the old map's frame)."""
    new = corridor_map(origin=(100.0, 100.0, 0.0))  # the old map's corridor, 100 m away
    loc.begin_map_preparation()
    with caplog.at_level(logging.INFO, logger="localization"):
        assert loc.set_initial_pose([102.0, 101.5, 0.0])
    assert "kept until the map" in caplog.text
    assert np.all(loc.particles()[:, 0] < 50.0)  # not applied on the old map
    loc.set_map(new)
    assert loc.ready and np.hypot(*(loc.estimate.pose[:2] - [102.0, 101.5])) < 0.3
    # a preparation that fails: the held pose goes to the map in use
    loc.begin_map_preparation()
    loc.set_initial_pose([103.0, 101.5, 0.0])
    loc.begin_map_preparation(False)
    assert np.hypot(*(loc.estimate.pose[:2] - [103.0, 101.5])) < 0.3


def test_a_scan_on_another_clock_is_not_moved_by_the_old_odometry():
    """Odometry ends at t = 0.1 s at 3 m/s; the next odometry and scan are stamped 1000 s later (a clock
    reset, a bag loop): the motion across the jump is unknown, so the particles are not carried on by the
    old twist for scan_max_wait (3 m/s × 0.5 s = 1.5 m) when that scan is used."""
    loc = Localizer(Parameters(num_particles=200, random_seed=1, ray_caster="distance_transform"))
    loc.set_map(corridor_map())
    for k in range(6):
        loc.on_odometry(TwistData(0.02 * k, 3.0, 0.0, 0.8))
    loc.set_initial_pose([5.0, 1.5, 0.0], stamp=0.05)
    loc.on_odometry(TwistData(1000.0, 0.0, 0.0, 0.0))  # the new clock's first message: a jump
    loc.on_scan(ScanData(1000.0, *good_scan()))
    loc.request_update()
    loc.flush()  # used with what the odometry knows (as at the end of a recording)
    assert_sane(loc)
    assert abs(np.mean(loc.particles()[:, 0]) - 5.0) < 0.5  # 0.15 m of the old history's motion at most


def test_before_any_map(caplog):
    loc = Localizer(Parameters(num_particles=50))
    with caplog.at_level(logging.INFO):
        assert loc.on_odometry(TwistData(0.0, 1.0, 0.0, 0.0)) is None
        assert loc.on_scan(ScanData(0.0, *good_scan())).estimate is None
    assert "no map" in caplog.text


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(stamp=FLOATS, vx=FLOATS, vy=FLOATS, wz=FLOATS, ranges=st.lists(FLOATS, max_size=60),
       amin=FLOATS, amax=FLOATS, inc=FLOATS, rmin=FLOATS, rmax=FLOATS)
def test_fuzz_callbacks_never_crash_or_emit_nan(loc, stamp, vx, vy, wz, ranges, amin, amax, inc, rmin, rmax):
    out = loc.on_odometry(TwistData(stamp, vx, vy, wz))
    if out is not None:
        assert np.all(np.isfinite(out.pose))
    out = loc.on_scan(ScanData(stamp, np.array(ranges, dtype=float), amin, amax, inc, rmin, rmax)).estimate
    if out is not None:
        assert np.all(np.isfinite(out.pose)) and np.all(np.isfinite(out.covariance))
    assert np.all(np.isfinite(loc.particles()))


def test_degenerate_filter_recovers_by_spreading_globally(caplog):
    m = corridor_map()
    loc = Localizer(Parameters(num_particles=300, random_seed=3, ray_caster="distance_transform"))
    loc.set_map(m)
    loc.set_initial_pose([5.0, 1.5, 0.0])
    loc._pf.particles[:, :2] = [-50.0, -50.0]  # the car was carried off: every particle impossible
    with caplog.at_level(logging.WARNING):
        for k in range(3):
            assert loc.on_scan(ScanData(float(k), *good_scan())).estimate is None
    assert "re-spreading" in caplog.text
    assert m.is_free(loc.particles()[:, :2]).mean() > 0.95
    assert_sane(loc)


def test_scan_stamped_long_before_the_odometry_is_ignored(loc, caplog):
    loc.on_odometry(TwistData(10.0, 0.0, 0.0, 0.0))
    loc.on_odometry(TwistData(10.02, 1.0, 0.0, 0.0))
    with caplog.at_level(logging.WARNING):
        assert loc.on_scan(ScanData(5.0, *good_scan())).estimate is None  # 5 s in the past: stale or a clock jump
    assert "before the latest odometry" in caplog.text
    assert loc.estimate.stamp == 10.02
    assert loc.on_scan(ScanData(10.01, *good_scan())).estimate is not None
    # a bag loop: odometry jumps back (reference reset), then scans of the new loop are used again
    assert loc.on_odometry(TwistData(0.0, 1.0, 0.0, 0.0)) is None
    loc.on_odometry(TwistData(0.02, 1.0, 0.0, 0.0))
    assert loc.on_scan(ScanData(0.01, *good_scan())).estimate is not None


def test_one_odometry_message_with_a_bad_stamp_loses_no_motion(loc):
    loc.on_odometry(TwistData(1.0, 0.0, 0.0, 0.0))
    x0 = loc.estimate.pose[0]
    loc.on_odometry(TwistData(1.02, 1.0, 0.0, 0.0))
    assert loc.on_odometry(TwistData(-2.0, 1.0, 0.0, 0.0)) is None  # one stamp 3 s back (corrupted, not a loop)
    est = loc.on_odometry(TwistData(1.06, 1.0, 0.0, 0.0))  # continues from 1.02: 0.04 s of motion
    assert est is not None and abs(est.pose[0] - x0 - 0.06) < 0.02



def test_the_localizer_says_why_it_could_not_use_a_scan():
    loc = Localizer(Parameters(num_particles=100, ray_caster="exact"))
    scan = ScanData(1.0, np.full(100, 2.0), -1.0, 1.0, 0.02, 0.1, 10.0)
    assert loc.on_scan(scan).ignored == "not ready"  # no map
    loc.begin_map_preparation()  # a map prepared off-thread, none installed yet
    assert loc.on_scan(scan).ignored == "map pending"
    loc.set_map(corridor_map())
    assert loc.on_scan(scan).ignored == "not ready"  # a map, no initial pose
    loc.set_initial_pose(np.array([2.0, 0.0, 0.0]), stamp=0.5)
    assert loc.on_scan(scan).ignored is None  # taken (it waits for odometry)
