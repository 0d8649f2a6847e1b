"""Time-correct localization: the odometry history on the scan's clock, estimates at
the scan's own time, thread safety, and scan deskew (kernel, accuracy, effect on a fast drive)."""
from __future__ import annotations

import math
import threading
from dataclasses import replace

import numpy as np
import pytest
from helpers import corridor_map, localize_recording

import localization.sim as S
from localization.core.geometry import compose, integrate_twist, integrate_twists, inverse
from localization.core.localizer import Localizer
from localization.core.localizer.pipeline import deskew_offsets
from localization.core.models.beam import BeamModel
from localization.core.occupancy_map import OccupancyMap
from localization.core.odometry import OdometryBuffer, TwistData
from localization.core.parameters import Parameters
from localization.core.paths import config_dir
from localization.core.raycast.exact import ExactRayCaster
from localization.core.scan import ScanData, beam_times
from localization.eval.datasets import trial_config
from localization.eval.reference import track_errors


@pytest.fixture(scope="module")
def stata(maps_dir) -> OccupancyMap:
    return OccupancyMap.from_yaml(maps_dir / "stata_basement.yaml")


# ------------------------------------------------------------------------------------ the odometry history


def _buffer(**kw) -> OdometryBuffer:
    buf = OdometryBuffer(**kw)
    for t, vx, wz in ((1.00, 9.0, 9.0), (1.02, 1.0, 0.0), (1.04, 2.0, 0.5), (1.06, 3.0, -0.5)):
        buf.add(TwistData(t, vx, 0.0, wz))
    return buf


def test_buffer_pieces_interpolate_and_extrapolate_by_hand():
    buf = _buffer()
    dts, twists = buf.segments(1.01, 1.09)
    # (1.01, 1.02] message 1.02; (1.02, 1.04] message 1.04; (1.04, 1.06] 1.06; then the last twist extrapolated
    assert dts == pytest.approx([0.01, 0.02, 0.02, 0.03])
    assert twists[:, 0] == pytest.approx([1.0, 2.0, 3.0, 3.0])
    expected = np.zeros(3)
    for dt, (vx, wz) in zip([0.01, 0.02, 0.02, 0.03], [(1.0, 0.0), (2.0, 0.5), (3.0, -0.5), (3.0, -0.5)]):
        expected = compose(expected, integrate_twist(vx, 0.0, wz, dt))
    assert buf.motion(1.01, 1.09) == pytest.approx(expected, abs=1e-15)
    assert buf.motion(1.09, 1.01) == pytest.approx(inverse(expected), abs=1e-12)  # backwards: the inverse
    # before the oldest stamp: its twist holds for buf.extrapolation (a recording that starts mid-drive), then nothing
    assert buf.motion(0.5, 1.0) == pytest.approx(integrate_twist(9.0, 0.0, 9.0, buf.extrapolation), abs=1e-12)
    assert buf.twist_at(1.0 - 0.5 * buf.extrapolation) == pytest.approx([9.0, 0.0, 9.0])
    assert buf.twist_at(1.0 - buf.extrapolation - 0.01) == pytest.approx(np.zeros(3))
    assert buf.twist_at(1.03) == pytest.approx([2.0, 0.0, 0.5]) and buf.twist_at(1.07) == pytest.approx([3, 0, -0.5])
    # the last twist is extrapolated at most buf.extrapolation: stopped odometry stops the particles
    far = buf.motion(1.06, 1.06 + buf.extrapolation + 5.0)
    assert far == pytest.approx(integrate_twist(3.0, 0.0, -0.5, buf.extrapolation), abs=1e-12)
    assert buf.twist_at(1.06 + buf.extrapolation + 0.01) == pytest.approx(np.zeros(3))


def test_buffer_corrections_and_time_offset():
    buf = _buffer(time_offset=-0.04, speed_scale=0.95, yaw_rate_scale=1.04, yaw_rate_bias=0.03)
    assert buf.latest == pytest.approx(1.02)  # stamped 1.06, describes the motion up to 1.02
    assert buf.twist_at(0.995) == pytest.approx([0.95 * 2.0, 0.0, 1.04 * 0.5 + 0.03])  # message 1.04 -> (0.98, 1.00]
    buf.trim(1.01)
    assert len(buf) == 2 and buf.oldest == pytest.approx(1.00)  # (1.00, 1.02] still holds 1.01


# ------------------------------------------------------------------------------------ the localizer


def _corridor_localizer(**overrides) -> Localizer:
    loc = Localizer(Parameters(num_particles=200, random_seed=1, ray_caster="distance_transform",
                               deterministic=True, **overrides))
    loc.set_map(corridor_map())
    loc.set_initial_pose([2.0, 1.5, 0.0])
    return loc


def _scan(stamp, time_increment=0.0, n=101):
    return ScanData(stamp, np.full(n, 0.9), -1.0, 1.0, 0.02, 0.02, 10.0, time_increment=time_increment)


def test_estimate_is_stamped_with_the_time_it_describes():
    loc = _corridor_localizer()
    for k in range(6):
        loc.on_odometry(TwistData(1.0 + 0.02 * k, 2.0, 0.0, 0.0))
    # a swept scan describes the middle of its sweep, newer than the odometry: it waits for it
    assert loc.on_scan(_scan(1.10, time_increment=1e-4)).estimate is None and loc.waiting_scans == 1
    out = loc.on_odometry(TwistData(1.12, 2.0, 0.0, 0.0))  # odometry reaches the scan's time: it is used
    (est,) = loc.take_corrections()
    assert est.stamp == pytest.approx(1.10 + 0.5 * 100 * 1e-4) and loc.waiting_scans == 0
    # each odometry message: that estimate carried forward to the message's time with the odometry since
    assert out.stamp == pytest.approx(1.12)
    assert out.pose == pytest.approx(compose(est.pose, [2.0 * (1.12 - est.stamp), 0.0, 0.0]), abs=1e-9)
    assert loc.estimate.stamp == pytest.approx(1.12)
    assert loc.estimate_at(est.stamp).pose == pytest.approx(est.pose, abs=1e-12)
    # a scan older than the particles' time (but covered by odometry): the particles go back exactly
    loc.request_update()  # (it has not moved since the last update)
    est2 = loc.on_scan(_scan(1.10)).estimate
    assert est2.stamp == pytest.approx(1.10)
    # without alignment: the scan is used at the newest odometry, without waiting
    off = _corridor_localizer(align_odometry=False)
    for k in range(6):
        off.on_odometry(TwistData(1.0 + 0.02 * k, 2.0, 0.0, 0.0))
    assert off.on_scan(_scan(1.10, time_increment=1e-4)).estimate.stamp == pytest.approx(1.10)


def test_odometry_during_a_blocked_sensor_update_is_not_lost_and_does_not_wait():
    """A sensor update held on another thread: each odometry message still gets its pose at once, the anchor
    carried through the whole history (the timeline's short lock, not the localizer's), and nothing is lost."""
    loc = _corridor_localizer()
    before = loc.on_odometry(TwistData(1.0, 0.0, 0.0, 0.0))
    real_update = loc._pf.sensor_update  # the first (tempered) update after the initial pose
    started, release = threading.Event(), threading.Event()

    def blocked_update(*args, **kwargs):
        started.set()
        assert release.wait(10.0)
        return real_update(*args, **kwargs)

    loc._pf.sensor_update = blocked_update
    result = []
    worker = threading.Thread(target=lambda: result.append(loc.on_scan(_scan(1.0)).estimate))
    worker.start()
    try:
        assert started.wait(5.0)
        for k in range(1, 6):  # 0.1 s of 1 m/s while the update is held
            est = loc.on_odometry(TwistData(1.0 + 0.02 * k, 1.0, 0.0, 0.0))
            assert worker.is_alive() and not release.is_set()  # returned while the update still holds the lock
            assert est is not None and est.stamp == pytest.approx(1.0 + 0.02 * k)
            assert est.pose == pytest.approx(compose(before.pose, [0.02 * k, 0.0, 0.0]), abs=1e-9)
            assert len(loc._inbox) == 0 and loc._timeline.latest == pytest.approx(1.0 + 0.02 * k)  # in the history
    finally:
        release.set()
        worker.join()
    loc._pf.sensor_update = real_update
    (updated,) = result
    assert updated.stamp == 1.0
    out = loc.on_odometry(TwistData(1.12, 1.0, 0.0, 0.0))  # the update's anchor carried through all of it
    assert out.pose == pytest.approx(compose(updated.pose, [0.12, 0.0, 0.0]), abs=1e-9)


def test_a_message_that_starts_a_new_history_waits_for_the_lock_holder():
    """A stamp jump during a held sensor update: that message (and the ones behind it) waits for the lock."""
    loc = _corridor_localizer()
    loc.on_odometry(TwistData(1.0, 0.0, 0.0, 0.0))
    results = []
    with loc._lock:  # as a sensor update holds it
        assert loc.on_odometry(TwistData(1.02, 1.0, 0.0, 0.0)) is not None  # the history goes on: no wait
        jump = threading.Thread(target=lambda: results.append(loc.on_odometry(TwistData(50.0, 1.0, 0.0, 0.0))))
        jump.start()
        jump.join(0.3)
        assert jump.is_alive() and len(loc._inbox) == 1  # a clock jump: waits for the lock holder
        assert loc._timeline.latest == pytest.approx(1.02)
    jump.join(5.0)
    assert not jump.is_alive() and len(loc._inbox) == 0
    est = loc.on_odometry(TwistData(50.02, 1.0, 0.0, 0.0))
    assert est is not None and est.stamp == pytest.approx(50.02)


def test_scans_due_says_when_the_odometry_reached_a_waiting_scan():
    loc = _corridor_localizer()
    loc.on_odometry(TwistData(1.0, 1.0, 0.0, 0.0))
    assert loc.on_scan(_scan(1.03)).used == ()  # waits for odometry past its time
    assert not loc.scans_due
    loc.on_odometry(TwistData(1.04, 1.0, 0.0, 0.0), run_scans=False)  # reaches it, leaves it to run_waiting
    assert loc.scans_due and loc.waiting_scans == 1
    loc.run_waiting()
    assert not loc.scans_due and loc.waiting_scans == 0
    assert [e.stamp for e in loc.take_corrections()][-1] == pytest.approx(1.03)


def _run(rec, params: Parameters):
    log, err = localize_recording(rec, params, load_stata())
    t, poses = log.estimates()
    late = err.t > 2.0  # after the convergence from the initial offset
    truth = track_errors(t, poses, rec.truth_t, rec.truth_poses)
    return float(err.ct_error[late].mean()), float(truth.along[truth.t > 2.0].mean())


_STATA = {}


def load_stata():
    if "m" not in _STATA:
        from localization.core.occupancy_map import load_map
        _STATA["m"] = load_map("stata_basement")
    return _STATA["m"]


@pytest.fixture(scope="module")
def fast_rec():
    """The first 7 s of the fast trial: 0 -> 7 m/s down the diagonal corridor, odometry 40 ms late."""
    return S.simulate(trial_config("fast", duration=7.0), load_stata())


def _params(**kw) -> Parameters:
    base = dict(num_particles=1000, random_seed=2, ray_caster="lookup_table", laser_offset_x=0.275)
    base.update(kw)
    return Parameters.from_yaml(config_dir() / "params.yaml", **base)


def test_alignment_with_the_right_time_offset_beats_no_alignment(fast_rec):
    aligned, along_aligned = _run(fast_rec, _params(odom_time_offset=-0.04))
    unaligned, along_unaligned = _run(fast_rec, _params(align_odometry=False, deskew=False))
    assert aligned < 0.8 * unaligned, (aligned, unaligned)
    assert abs(along_aligned) < abs(along_unaligned)
    assert abs(along_aligned) < 0.02


def test_deskew_reduces_the_error_on_the_fast_trial(fast_rec):
    deskewed, _ = _run(fast_rec, _params(odom_time_offset=-0.04))
    skewed, _ = _run(fast_rec, _params(odom_time_offset=-0.04, deskew=False))
    assert deskewed < skewed, (deskewed, skewed)


# ------------------------------------------------------------------------------------ the deskew kernel


def _sweep_offsets(laser, vx=7.0, wz=0.8, beams=100, sweep=0.01875):
    """Per-beam laser motion over a sweep around its middle (as the localizer computes it)."""
    dt = np.linspace(-0.5 * sweep, 0.5 * sweep, beams)
    robot = integrate_twists(vx, 0.0, wz, dt)
    return compose(inverse(laser), compose(robot, laser)), robot


@pytest.mark.parametrize("caster", ["lookup_table", "lookup_table_exact"])
def test_deskew_kernel_equals_its_numpy_reference(stata, caster):
    model = BeamModel(ray_caster=caster, laser_offset=(0.275, 0.02, 0.01), table_width=201, occupancy_map=stata)
    rng = np.random.default_rng(5)
    particles = np.column_stack([rng.normal(-12.0, 0.3, 300), rng.normal(14.5, 0.3, 300), rng.normal(-2.2, 0.1, 300)])
    angles = np.linspace(-2.35, 2.35, 100)
    offsets, _ = _sweep_offsets(model.laser_offset)
    observation = model.expected_ranges(particles[:1], angles, offsets)[0] + rng.normal(0, 0.02, angles.size)
    fast = model.log_likelihood(particles, observation, angles, offsets=offsets)
    ref = model.log_likelihood_numpy(particles, observation, angles, offsets=offsets)
    assert np.array_equal(np.isneginf(fast), np.isneginf(ref))
    finite = np.isfinite(ref)
    assert finite.sum() > 200
    if caster == "lookup_table":
        assert np.allclose(fast[finite], ref[finite], rtol=1e-12, atol=1e-9)
    else:  # the exact finish marches from the beam's own origin; the reference casts exactly from it
        assert np.median(np.abs(fast[finite] - ref[finite])) < 0.5
    # zero offsets are the rigid scan
    rigid = model.log_likelihood(particles, observation, angles)
    assert np.array_equal(model.log_likelihood(particles, observation, angles, offsets=np.zeros((100, 3))), rigid)
    assert not np.allclose(fast[finite], rigid[finite])


def test_deskewed_ranges_match_exact_casting_from_each_beams_pose(stata):
    model = BeamModel(ray_caster="lookup_table", laser_offset=(0.275, 0.0, 0.0), occupancy_map=stata)
    exact = ExactRayCaster(stata, model.max_range)
    angles = np.linspace(-2.35, 2.35, 100)
    poses = np.array([[-12.5, 14.5, -2.2], [-30.0, -0.4, 3.1], [-54.8, 15.0, 1.57], [-35.0, 34.1, 0.0]])
    errors_deskewed, errors_rigid = [], []
    for pose in poses:
        offsets, robot = _sweep_offsets(model.laser_offset)
        truth_poses = compose(compose(pose, robot), model.laser_offset)  # the laser at each beam's time
        truth = exact.cast_rays(truth_poses, angles + 0.0)
        got = model.expected_ranges(pose[None], angles, offsets)[0]
        rigid = model.expected_ranges(pose[None], angles)[0]
        ok = truth < model.max_range - 0.5
        errors_deskewed.append(np.abs(got - truth)[ok])
        errors_rigid.append(np.abs(rigid - truth)[ok])
    dsk, rig = np.concatenate(errors_deskewed), np.concatenate(errors_rigid)
    assert np.median(dsk) < 0.02 and np.mean(dsk < 0.05) > 0.9, (np.median(dsk), np.mean(dsk < 0.05))
    assert np.median(dsk) < 0.5 * np.median(rig)


def test_swept_scan_gets_offsets_only_with_sweep_timing():
    loc = _corridor_localizer(num_beams_per_particle=101)
    for k in range(6):
        loc.on_odometry(TwistData(1.0 + 0.02 * k, 2.0, 0.0, 0.4))
    scan = _scan(1.10, time_increment=1e-4)
    t_s = loc.scan_time(scan)
    twist = loc._timeline.twist_at(1.09)  # the twist holding at the scan's time
    offsets = deskew_offsets(beam_times(scan, np.arange(101)), t_s, twist, loc.laser_offset)
    assert offsets.shape == (101, 3)
    # the first beam 5 ms before the middle, the last 5 ms after: ∓ 1 cm at 2 m/s
    assert offsets[0, 0] == pytest.approx(-0.01, abs=1e-3) and offsets[-1, 0] == pytest.approx(0.01, abs=1e-3)
    assert offsets[50] == pytest.approx(np.zeros(3), abs=1e-12)
    assert beam_times(_scan(1.10), np.arange(101)) is None  # no sweep timing
    assert deskew_offsets(None, t_s, twist, loc.laser_offset) is None
    assert math.isfinite(t_s) and replace(scan, time_increment=1.0).time_increment == 1.0
    assert loc.scan_time(replace(scan, time_increment=1.0)) == scan.stamp  # not a lidar sweep: ignored


def test_a_car_that_stops_gets_one_more_update_where_it_stands():
    loc = _corridor_localizer(update_min_distance=0.5, update_min_angle=0.5)
    loc.on_odometry(TwistData(1.0, 0.0, 0.0, 0.0))
    assert loc.on_scan(_scan(1.0)).estimate is not None  # the first scan after the initial pose
    for k in range(1, 6):
        loc.on_odometry(TwistData(1.0 + 0.02 * k, 1.0, 0.0, 0.0))  # 0.1 m: below update_min_distance
    assert loc.on_scan(_scan(1.1)).estimate is None
    for k in range(6, 11):
        loc.on_odometry(TwistData(1.0 + 0.02 * k, 0.0, 0.0, 0.0))  # stopped
    assert loc.on_scan(_scan(1.17)).estimate is not None  # once where it stopped ...
    assert loc.on_scan(_scan(1.2)).estimate is None  # ... and not again while it stands
