"""Slip and skid: odometry that changes speed faster than the tyres' grip allows
(``odom_max_acceleration``) spreads the particles along track over the difference."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from helpers import localize_recording

from localization.core.models.motion import MotionModel
from localization.core.odometry import OdometryBuffer, TwistData
from localization.core.parameters import Parameters
from localization.core.paths import config_dir
from localization.eval.datasets import trial_config
from localization.sim import recorder as S

RATE = 50.0  # Hz, the VESC's odometry


def _braking(a_max: float, v0: float = 2.0, until: float = 1.0) -> OdometryBuffer:
    """Odometry at RATE: v0 until t = 0, then a reported stop at once (locked wheels) until ``until``."""
    buf = OdometryBuffer(max_acceleration=a_max)
    for t in np.arange(-0.5, until + 1e-9, 1.0 / RATE):
        buf.add(TwistData(float(t), v0 if t <= 1e-9 else 0.0, 0.0, 0.0))
    return buf


def _spread(buf: OdometryBuffer, t0: float, t1: float, cuts: int) -> tuple[float, float]:
    """Summed slip mean and variance over [t0, t1] asked for in ``cuts`` pieces."""
    edges = np.linspace(t0, t1, cuts + 1)
    mean = var = 0.0
    for a, b in zip(edges[:-1], edges[1:]):
        _, _, slips = buf.slip_segments(a, b)
        mean += slips[:, 0].sum()
        var += slips[:, 1].sum()
    return mean, var


def test_a_reported_stop_is_a_skid_of_v_squared_over_two_a():
    buf = _braking(a_max=5.0)
    mean, var = _spread(buf, -0.5, 1.0, 1)
    # m: the car slows at 5 m/s² from 2 m/s while the odometry says 0, v²/2a, less half a message's travel (the
    # grip-limited speed steps down once per message)
    slide = 2.0 ** 2 / (2 * 5.0) - 0.5 * 2.0 / RATE
    assert 2 * mean == pytest.approx(slide, rel=1e-6)  # mean half of it ...
    assert np.sqrt(var) == pytest.approx(slide / 2, rel=1e-6)  # ... std half of it: 0 .. slide at one sigma
    # before the brake nothing slips; once the grip-limited speed reached 0 nothing slips either
    assert _spread(buf, -0.5, 0.0, 1) == (0.0, 0.0)
    assert _spread(buf, 0.5, 1.0, 1) == (0.0, 0.0)


@pytest.mark.parametrize("cuts", [1, 3, 17, 60])
def test_the_spread_of_a_skid_does_not_depend_on_how_it_is_cut(cuts):
    # one unknown (the real grip) for the whole skid: finer pieces must not shrink the spread
    buf = _braking(a_max=5.0)
    want = _spread(buf, -0.5, 1.0, 1)
    assert _spread(buf, -0.5, 1.0, cuts) == pytest.approx(want, rel=1e-9)


def test_without_a_grip_limit_odometry_never_slips_and_travel_is_the_odometry_s():
    buf = _braking(a_max=0.0)
    assert _spread(buf, -0.5, 1.0, 1) == (0.0, 0.0)
    assert buf.travel(0.0, 1.0)[0] == pytest.approx(0.0, abs=1e-12)
    # with it, the skid counts as travel: the update policy keeps updating while the car slides
    assert _braking(a_max=5.0).travel(0.0, 1.0)[0] == pytest.approx(0.38, rel=1e-6)


def test_speed_changes_within_the_grip_do_not_slip_and_wheel_spin_slips_backwards():
    buf = OdometryBuffer(max_acceleration=5.0)
    for k, t in enumerate(np.arange(0.0, 1.0, 1.0 / RATE)):
        buf.add(TwistData(float(t), min(3.0 * t, 2.0), 0.0, 0.0))  # 3 m/s² < 5: real acceleration
    assert _spread(buf, 0.0, 1.0, 1) == (0.0, 0.0)
    spin = OdometryBuffer(max_acceleration=5.0)
    for t in np.arange(0.0, 0.5, 1.0 / RATE):
        spin.add(TwistData(float(t), 0.0 if t < 0.1 else 2.0, 0.0, 0.0))  # 0 -> 2 m/s in one message: spin
    mean, var = _spread(spin, 0.0, 0.5, 1)
    assert mean == pytest.approx(-0.5 * 2.0 ** 2 / (2 * 5.0), rel=0.1) and var > 0


def test_a_history_restarted_after_a_clock_jump_does_not_spin_from_its_marker():
    from localization.core.localizer.timeline import OdometryLimits, OdometryTimeline
    tl = OdometryTimeline(OdometryLimits(max_acceleration=5.0))
    for t in np.arange(0.0, 1.0, 1.0 / RATE):
        assert tl.add(TwistData(float(t), 2.0, 0.0, 0.0)).accepted
    tl.add(TwistData(100.0, 2.0, 0.0, 0.0))  # the clock jumps (a bag loop): refused, the history restarts ...
    for t in np.arange(100.0 + 1.0 / RATE, 101.0, 1.0 / RATE):
        assert tl.add(TwistData(float(t), 2.0, 0.0, 0.0)).accepted
    _, _, slips = tl.slip_segments(100.0, 101.0)  # ... from a marker that is not a stop: still 2 m/s, no slip
    assert np.abs(slips).max() == 0.0


def test_the_motion_model_moves_the_slip_mean_along_the_heading_with_its_variance():
    mm = MotionModel(rng=1, a_trans=0.0, a_lateral=0.0, a_rot=0.0, a_rot_to_trans=0.0, a_trans_to_rot=0.0,
                     floor_xy=0.0, floor_theta=0.0)
    p = np.tile([1.0, 2.0, np.pi / 2], (20000, 1))  # heading +y
    out = mm.evaluate(p, [0.0, 0.0, 0.0], slip=0.2, slip_var=0.01)
    assert out[:, 1].mean() == pytest.approx(2.2, abs=0.003)  # along the heading
    assert out[:, 1].std() == pytest.approx(0.1, rel=0.03)
    assert np.abs(out[:, 0] - 1.0).max() < 1e-9  # nothing across it
    exact = MotionModel(deterministic=True).evaluate(p[:3], [0.1, 0.0, 0.0], slip=0.2, slip_var=0.01)
    assert np.allclose(exact[:, :2], [[1.0, 2.1]] * 3)  # deterministic: the odometry exactly, no slip


def _skid_recording():
    """A 3 m/s drive down the Stata basement that brakes to a stop at its end (the simulated car slows at
    ~1.5 m/s²) while the odometry reports the stop at once: the wheels locked, the car slides ~3 m."""
    cfg = replace(trial_config("trial1_noise0"), speed=3.0, duration=21.0, odom_noise=0.05)
    from localization.core.occupancy_map import load_map
    m = load_map("stata_basement")
    rec = S.simulate(cfg, m)
    o = rec.odometry
    v = o.true_twist[:, 0]
    slowing = np.flatnonzero(v < 0.97 * cfg.speed)
    brake = slowing[slowing > len(v) // 2][0]
    twist = o.twist.copy()
    twist[brake:] = 0.0
    return replace(rec, odometry=replace(o, twist=twist)), m, float(o.t[brake])


def test_a_skid_is_followed_with_the_grip_limit_and_lost_without():
    rec, m, brake = _skid_recording()
    end = {}
    for a in (0.0, 1.5):  # 1.5 m/s²: how hard the simulated car brakes
        p = Parameters.from_yaml(config_dir() / "params.yaml", num_particles=1000, random_seed=1,
                                 odom_max_acceleration=a)
        _, err = localize_recording(rec, p, m)
        assert err.ct_error[(err.t > 1.0) & (err.t < brake)].mean() < 0.03  # the same before the brake
        end[a] = float(err.ct_error[err.t > brake + 1.2].mean())
    assert end[0.0] > 1.0  # the odometry's stop is believed: the estimate stays metres behind
    assert end[1.5] < 0.1


@pytest.mark.parametrize("max_acceleration", [0.0, 6.0])
def test_the_compiled_pieces_equal_their_numpy_reference(max_acceleration):
    """OdometryBuffer.slip_segments (one compiled pass) and slip_segments_numpy: the same pieces, twists and slips,
    bit for bit, for spans inside, across and beyond the history (extrapolated), braking and spinning."""
    rng = np.random.default_rng(3)
    buf = OdometryBuffer(time_offset=0.129, speed_scale=1.05, extrapolation=0.5, max_acceleration=max_acceleration)
    t, v = 10.0, 2.0
    for _ in range(60):
        t += rng.uniform(0.01, 0.03)
        v = max(0.0, v + rng.choice([-1.5, 0.0, 0.0, 1.2]))  # sudden stops and spins: slips
        buf.add(TwistData(t, v, rng.normal(0, 0.05), rng.normal(0, 0.3)))
    t0, t1 = buf.oldest, buf.latest
    spans = [(t0 + 0.1, t0 + 0.13), (t0 - 0.7, t0 + 0.2), (t1 - 0.05, t1 + 0.3), (t1 + 0.1, t1 + 0.9),
             (t0 - 2.0, t1 + 2.0), (t0 + 0.2, t0 + 0.2)] + [tuple(sorted(rng.uniform(t0 - 0.6, t1 + 0.6, 2)))
                                                             for _ in range(50)]
    for a, b in spans:
        fast, ref = buf.slip_segments(a, b), buf.slip_segments_numpy(a, b)
        for x, y in zip(fast, ref):
            assert x.shape == y.shape and np.array_equal(x, y)
    assert (buf.slip_segments(t0, t1)[2] != 0).any() == (max_acceleration > 0)


def test_the_history_arrays_hold_the_messages_as_they_come_and_go():
    """The arrays the compiled queries read (written as messages come, trimmed by moving their first row)
    always hold the buffer's messages: over adds, trims past the arrays' room, and a reset."""
    rng = np.random.default_rng(5)
    buf = OdometryBuffer(max_acceleration=6.0)
    t = 0.0
    for step in range(600):
        t += rng.uniform(0.01, 0.03)
        buf.add(TwistData(t, rng.uniform(0, 3), rng.normal(0, 0.05), rng.normal(0, 0.3)))
        if step % 7 == 0:
            buf.trim(t - rng.uniform(0.0, 2.0 if step < 300 else 0.2))  # long, then short histories
        if step == 450:
            buf.reset()
        stamps, twists, slips, slipped = buf._as_arrays()
        assert np.array_equal(stamps, np.asarray(buf._t))
        assert np.array_equal(twists, np.asarray(buf._twist).reshape(-1, 3))
        assert np.array_equal(slips, np.asarray(buf._slip)) and np.array_equal(slipped, np.asarray(buf._slipped))
        assert twists.shape == (len(buf), 3) and stamps.flags.c_contiguous
