"""A differential-drive base in the simulator (kinematics, turns on the spot, wheel-encoder odometry)
and the localizer tracking it with robot_model_type differential."""
from __future__ import annotations

import logging
import math
from dataclasses import replace

import numpy as np
import pytest

import localization.sim as S
from localization.bags import bag_info, read_messages
from localization.benchmarks import robustness as RB
from localization.core.geometry import compose, relative
from localization.core.localizer import Localizer
from localization.core.occupancy_map import OccupancyMap
from localization.core.parameters import Parameters
from localization.tools import simulate as simulate_cli


@pytest.fixture(scope="module")
def stata(maps_dir) -> OccupancyMap:
    return OccupancyMap.from_yaml(maps_dir / "stata_basement.yaml")


@pytest.fixture(scope="module")
def recording(stata):
    return S.simulate(S.differential_trial(), stata)


def on_the_spot(traj) -> np.ndarray:
    """Physics steps turning on the spot."""
    return (np.abs(traj.v) < 0.01) & (np.abs(traj.w) > 0.3)


def test_wheel_kinematics():
    base = S.DiffDriveModel()
    left, right = base.wheel_rates(0.0, 1.0)  # on the spot: the wheels turn against each other
    assert left == pytest.approx(-right) and right == pytest.approx(0.5 * base.track / base.wheel_radius)
    left, right = base.wheel_rates(0.5, 0.3)
    v, w = base.twist_from_wheels(left * 0.05, right * 0.05, 0.05)
    assert (v, w) == pytest.approx((0.5, 0.3))
    assert base.yaw_rate(0.0, 0.7) == 0.7 and base.steering(0.7) == 0.0
    v, w = base.limit(0.0, 0.0, 5.0, 5.0, dt=10.0)
    assert (v, w) == (base.max_speed, base.max_yaw_rate)
    v, w = base.limit(0.0, 0.0, 5.0, -5.0, dt=0.005)
    assert (v, w) == pytest.approx((base.max_accel * 0.005, -base.max_yaw_accel * 0.005))
    assert base.step(np.zeros(3), 0.0, 1.0, 0.5) == pytest.approx([0.0, 0.0, 0.5])


def test_trial_turns_on_the_spot_and_drives_the_route(recording):
    traj, cfg = recording.trajectory, recording.cfg
    spot = on_the_spot(traj)
    turned = np.abs(traj.w[spot]).sum() / S.PHYSICS_RATE_HZ
    assert turned > 4.0  # a U-turn and three more turns, all on the spot
    starts = np.flatnonzero(np.diff(spot.astype(int)) == 1)
    assert len(starts) >= 4
    assert np.all(traj.steer == 0.0) and np.abs(traj.v).max() <= cfg.car.max_speed + 1e-9
    assert traj.min_clearance > cfg.car.radius + 0.2
    assert np.hypot(*(traj.poses[-1, :2] - np.asarray(cfg.waypoints[-1]))) < 0.15
    # pure turning leaves the position where it is
    k = np.flatnonzero(spot)
    assert np.hypot(*(traj.poses[k + 1, :2] - traj.poses[k, :2]).T).max() < 1e-3


def test_wheel_encoder_odometry(recording, stata):
    cfg, odom = recording.cfg, recording.odometry
    assert np.all(odom.twist[:, 1] == 0.0)  # encoders cannot see sideways motion
    assert np.diff(odom.t) == pytest.approx(1.0 / cfg.odom_rate)
    base = cfg.car
    tick = 2 * math.pi / base.encoder_ticks * base.wheel_radius / (1.0 / cfg.odom_rate)  # m/s of one tick
    # without slip the reported speed is the true one up to one tick per wheel and period
    exact = S.odometry_from_trajectory(recording.trajectory, replace(cfg, car=replace(base, wheel_slip=0.0)),
                                       np.random.default_rng(0))
    assert np.abs(exact.twist[:, 0] - exact.true_twist[:, 0]).max() <= tick + 1e-9
    assert np.abs(exact.twist[:, 2] - exact.true_twist[:, 2]).max() <= 2 * tick / base.track + 1e-9
    # with slip the odometry drifts: its end pose is off the truth, by centimetres to decimetres
    end = compose(recording.trajectory.poses[0], odom.pose[-1])
    miss = np.hypot(*(end[:2] - recording.trajectory.poses[-1, :2]))
    assert 0.01 < miss < 1.0
    # the bag: odometry with vy = 0, turns on the spot in the reported twist
    drift = relative(compose(recording.trajectory.poses[0], exact.pose[-1]), recording.trajectory.poses[-1])
    assert np.hypot(*drift[:2]) < 0.1


def test_cli_records_a_differential_drive(tmp_path, capsys):
    out = tmp_path / "diff"
    assert simulate_cli.main([str(out), "--robot", "differential", "--duration", "8"]) == 0
    assert "wrote" in capsys.readouterr().out
    info = bag_info(out)
    assert info.topics["/scan"].count == 81 and info.topics["/odom"].count == 161  # 10 Hz lidar, 20 Hz odometry
    odoms = [m.msg for m in read_messages(out, ["/odom"])]
    assert all(m.twist.twist.linear.y == 0.0 for m in odoms)
    assert max(abs(m.twist.twist.angular.z) for m in odoms) > 0.5  # the U-turn on the spot has begun


def localize(rec, stata, robot="differential", **overrides):
    values = dict(ray_caster="lookup_table_exact", num_particles=800, robot_model_type=robot, random_seed=3,
                  laser_offset_x=rec.cfg.laser_offset[0])
    values.update(overrides)
    loc = Localizer(Parameters(values), logging.getLogger("test.differential"))
    loc.set_map(stata)
    run = RB.run_recording(rec, loc, init="pose")
    return RB.ct_errors(rec, run)


def test_localizer_tracks_the_differential_drive(recording, stata):
    cmp = localize(recording, stata)
    assert cmp.ct_error.size > 500 and np.all(np.isfinite(cmp.ct_error))
    assert cmp.ct_error.mean() <= 0.03, cmp.ct_error.mean()
    late = cmp.t > 1.0  # after the first scans pulled the cloud from the offset initial pose
    assert np.percentile(cmp.ct_error[late], 95) < 0.06
    assert np.degrees(cmp.heading_error[late].mean()) < 1.0
    # turning on the spot: the heading follows (the position error stays small too)
    traj = recording.trajectory
    spot_t = traj.t[:-1][on_the_spot(traj)]
    during = np.isin(np.round(cmp.t * S.PHYSICS_RATE_HZ).astype(int), np.round(spot_t * S.PHYSICS_RATE_HZ).astype(int))
    assert during.sum() > 50
    assert cmp.ct_error[during].max() < 0.08 and np.degrees(cmp.heading_error[during].max()) < 3.0


def test_sideways_odometry_of_a_differential_base_is_ignored_with_one_warning(recording, stata, caplog):
    """Odometry claiming sideways motion (a broken driver): the differential model drops it."""
    twist = recording.odometry.twist.copy()
    twist[:, 1] = 0.05  # 5 cm/s sideways, never true
    noisy = replace(recording, odometry=replace(recording.odometry, twist=twist))
    with caplog.at_level(logging.WARNING, logger="localization.motion"):
        cmp = localize(noisy, stata)
    said = [r for r in caplog.records if r.name == "localization.motion"]
    assert len(said) == 1 and "vy" in said[0].getMessage()
    assert cmp.ct_error.mean() <= 0.03
