"""Simulator timing effects: odometry latency, scale and bias, lidar sweep timing, range
scale, laser mounting offset, driving at 7 m/s."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

import localization.sim as S
from localization.bags import read_messages, stamp_to_ns
from localization.core.geometry import compose, yaw_of
from localization.core.occupancy_map import OccupancyMap
from localization.core.raycast.exact import ExactRayCaster
from localization.eval.datasets import SIM_TRIALS, trial_config


@pytest.fixture(scope="module")
def stata(maps_dir) -> OccupancyMap:
    return OccupancyMap.from_yaml(maps_dir / "stata_basement.yaml")


@pytest.fixture(scope="module")
def fast_traj(stata):
    return S.simulate_trajectory(trial_config("fast"), stata)


def test_new_config_fields_and_defaults():
    cfg = S.SimConfig()
    assert (cfg.odom_latency, cfg.speed_scale, cfg.yaw_rate_scale, cfg.yaw_rate_bias) == (0.0, 1.0, 1.0, 0.0)
    assert (cfg.sweep, cfg.laser_offset, cfg.range_scale) == (False, (0.275, 0.0, 0.0), 1.0)
    fast, cal = SIM_TRIALS["fast"].config, SIM_TRIALS["calibration"].config
    assert fast.odom_latency == 0.04 and fast.sweep and fast.odom_noise == 0.3 and 6.0 <= fast.speed <= 7.0
    assert cal.sweep and cal.odom_latency > 0 and cal.speed_scale != 1 and cal.yaw_rate_scale != 1
    assert cal.yaw_rate_bias != 0 and cal.laser_offset != (0.275, 0.0, 0.0) and cal.range_scale != 1


def test_odometry_latency_reports_the_twist_late(stata):
    cfg = trial_config("trial1_noise0", duration=3.0)  # accelerating from standstill: the twist changes
    traj = S.simulate_trajectory(cfg, stata)
    on_time = S.odometry_from_trajectory(traj, cfg, np.random.default_rng(0))
    late = S.odometry_from_trajectory(traj, replace(cfg, odom_latency=0.04), np.random.default_rng(0))
    assert np.array_equal(late.t, on_time.t)
    # 40 ms = two 50 Hz periods: message k reports what message k-2 reports without latency
    assert late.twist[2:] == pytest.approx(on_time.twist[:-2], abs=1e-12)
    assert np.all(late.twist[:2] == 0.0)  # the car stood still before t = 0
    assert np.abs(on_time.twist[2:, 0] - on_time.twist[:-2, 0]).max() > 0.05  # the shift is visible
    # 30 ms: the mean true speed over (t - 0.05, t - 0.03], integrated by hand from the physics steps
    odd = S.odometry_from_trajectory(traj, replace(cfg, odom_latency=0.03), np.random.default_rng(0))
    k = 40
    t_end = odd.t[k] - 0.03
    steps = np.arange(len(traj.v))
    lo, hi = traj.t[steps], traj.t[steps] + 1.0 / S.PHYSICS_RATE_HZ
    overlap = np.clip(np.minimum(hi, t_end) - np.maximum(lo, t_end - 0.02), 0.0, None)
    assert odd.twist[k, 0] == pytest.approx(np.sum(traj.v * overlap) / 0.02, abs=1e-12)


def test_odometry_scales_and_bias(stata):
    cfg = trial_config("trial2_noise0.3", duration=4.0, odom_noise=0.0)
    traj = S.simulate_trajectory(cfg, stata)
    clean = S.odometry_from_trajectory(traj, cfg, np.random.default_rng(0))
    biased = S.odometry_from_trajectory(traj, replace(cfg, speed_scale=0.95, yaw_rate_scale=1.04, yaw_rate_bias=0.03),
                                        np.random.default_rng(0))
    assert biased.twist[:, 0] == pytest.approx(0.95 * clean.twist[:, 0], abs=1e-12)
    assert biased.twist[:, 2] == pytest.approx(1.04 * clean.twist[:, 2] + 0.03, abs=1e-12)


def test_sweep_timing_in_the_message_and_in_the_ranges(tmp_path, stata):
    cfg = trial_config("fast", duration=3.0, range_noise=0.0)
    rec = S.record(cfg, tmp_path / "bag", occupancy_map=stata)
    dt = (rec.scan_angle_increment / (2 * math.pi)) / cfg.scan_rate
    assert rec.scan_time_increment == pytest.approx(dt) and 1080 * dt == pytest.approx(0.01875)
    scans = [m for m in read_messages(tmp_path / "bag", ["/scan"])]
    k = len(scans) - 5  # a sweep well inside the trajectory
    msg = scans[k].msg
    assert msg.time_increment == pytest.approx(dt) and msg.scan_time == pytest.approx(0.025)
    stamp = (stamp_to_ns(msg.header.stamp) - stamp_to_ns(scans[0].msg.header.stamp)) * 1e-9
    assert stamp == pytest.approx(rec.scan_t[k], abs=1e-9)  # the header stamp is the first beam's time
    assert rec.trajectory.v[-20:].mean() > 4.0  # the car is moving fast during these sweeps
    # every beam cast from the laser pose at its own time
    lidar = S.Lidar(stata, cfg, np.random.default_rng(0))
    times = rec.scan_t[k] + np.arange(1081) * dt
    laser = compose(rec.trajectory.pose_at(times), cfg.laser_offset)
    exact = ExactRayCaster(stata, cfg.range_max).cast_rays(laser, lidar.angles)
    z = np.asarray(msg.ranges, dtype=float)
    ok = exact < cfg.range_max - 0.01
    assert z[ok] == pytest.approx(exact[ok], abs=1e-5)
    # ... and not from the pose at the stamp (the car moves ~0.1 m during the sweep)
    static = ExactRayCaster(stata, cfg.range_max).cast(laser[:1], lidar.angles)[0]
    assert np.abs(z[ok] - static[ok]).max() > 0.05
    assert np.hypot(*(laser[-1, :2] - laser[0, :2])) > 0.075


def test_no_sweep_keeps_time_increment_zero(stata):
    rec = S.simulate(trial_config("trial1_noise0", duration=0.5), stata)
    assert rec.scan_time_increment == 0.0


def test_range_scale(stata):
    cfg = trial_config("trial2_noise0.3", range_noise=0.0)
    poses = np.array([cfg.start, [-12.0, 25.7, math.pi]])
    plain = S.Lidar(stata, cfg, np.random.default_rng(1)).scan(poses)
    scaled = S.Lidar(stata, replace(cfg, range_scale=1.01), np.random.default_rng(1)).scan(poses)
    inner = plain < 9.0
    assert scaled[inner] == pytest.approx(1.01 * plain[inner], rel=1e-6)


def test_laser_offset_in_tf_static_and_in_the_ranges(tmp_path, stata):
    offset = (0.30, 0.02, 0.015)
    cfg = trial_config("trial1_noise0", duration=0.3, laser_offset=offset, range_noise=0.0)
    rec = S.record(cfg, tmp_path / "bag", occupancy_map=stata)
    tf = next(iter(read_messages(tmp_path / "bag", ["/tf_static"]))).msg.transforms[0]
    assert (tf.header.frame_id, tf.child_frame_id) == ("base_link", "laser")
    tr = tf.transform.translation
    assert (tr.x, tr.y, yaw_of(tf.transform.rotation)) == pytest.approx(offset, abs=1e-9)
    lidar = S.Lidar(stata, cfg, np.random.default_rng(0))
    expected = ExactRayCaster(stata, cfg.range_max).cast(compose(rec.trajectory.poses[0], offset), lidar.angles)[0]
    ok = expected < 9.9
    assert rec.scan_ranges[0][ok] == pytest.approx(expected[ok], abs=1e-5)


def test_seven_metres_per_second_stays_on_the_route(fast_traj):
    cfg = trial_config("fast")
    traj = fast_traj
    assert traj.v.max() >= 6.5 and traj.v.max() <= cfg.car.max_speed
    assert np.sum(traj.v > 6.0) / S.PHYSICS_RATE_HZ > 5.0  # seconds above 6 m/s
    path = S.densify(cfg.waypoints, 0.05)
    d = np.min(np.hypot(traj.poses[::10, None, 0] - path[None, :, 0], traj.poses[::10, None, 1] - path[None, :, 1]),
               axis=1)
    fast = traj.v[::10] > 5.0
    assert d[fast].max() < 0.3  # on the straights the car tracks the centre line
    assert d[60:].max() < 1.0  # and it never cuts a corner by a metre (after joining the route in 3 s)
    assert traj.min_clearance > cfg.car.radius + 0.1
    lateral = np.abs(traj.v * traj.w)
    assert lateral.max() < 1.3 * cfg.car.max_lateral_accel


def test_pose_at_interpolates_the_physics_steps(fast_traj):
    traj = fast_traj
    assert traj.pose_at(traj.t[:50]) == pytest.approx(traj.poses[:50], abs=1e-9)
    mid = traj.pose_at(traj.t[1000] + 0.0025)
    assert mid[:2] == pytest.approx(0.5 * (traj.poses[1000, :2] + traj.poses[1001, :2]), abs=1e-3)
