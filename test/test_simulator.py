"""localization-simulate: kinematics, controller, sensors, bag contents, determinism, caching."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

import localization.sim as S
from localization.bags import bag_info, read_messages, stamp_to_ns
from localization.core.geometry import compose, integrate_twist, relative, yaw_of
from localization.core.occupancy_map import OccupancyMap
from localization.core.raycast.exact import ExactRayCaster
from localization.eval import datasets
from localization.eval.datasets import REAL_BAGS, SIM_TRIALS, real_bag_path, sim_bag, trial_config
from localization.ros.conversions import stamp_to_sec
from localization.tools import simulate as simulate_cli


@pytest.fixture(scope="module")
def stata(maps_dir) -> OccupancyMap:
    return OccupancyMap.from_yaml(maps_dir / "stata_basement.yaml")


def _box_map(size=10.0, res=0.05) -> OccupancyMap:
    n = int(size / res)
    grid = np.zeros((n, n), dtype=np.int8)
    grid[0, :] = grid[-1, :] = grid[:, 0] = grid[:, -1] = 100
    return OccupancyMap(grid, res, (-size / 2, -size / 2, 0.0))


# ------------------------------------------------------------------ kinematics and control


def test_arc_matches_numerical_integration():
    car = S.CarModel()
    v, steer, dt = 2.0, 0.3, 0.4
    w = car.yaw_rate(v, steer)
    assert w == pytest.approx(v * math.tan(steer) / 0.325)
    pose = np.zeros(3)
    n = 100000  # Riemann sum of (v cos θ, v sin θ) with θ = w t
    th = (np.arange(n) + 0.5) * (w * dt / n)
    x = np.sum(v * np.cos(th)) * dt / n
    y = np.sum(v * np.sin(th)) * dt / n
    exact = car.step(pose, v, steer, dt)
    assert exact == pytest.approx([x, y, w * dt], abs=1e-4)
    straight = car.step(pose, v, 0.0, dt)
    assert straight == pytest.approx([v * dt, 0.0, 0.0], abs=1e-12)


def test_minimum_turning_radius_and_limits():
    car = S.CarModel()
    assert car.wheelbase == 0.325 and car.max_speed == 8.0 and car.max_steer == 0.34
    assert S.SimConfig().laser_offset == (0.275, 0.0, 0.0)
    v, steer = car.limit(0.0, 0.0, 10.0, 1.0, dt=10.0)  # huge dt: only the absolute limits bind
    assert v == 8.0 and steer == 0.34
    v, steer = car.limit(0.0, 0.0, 10.0, 1.0, dt=0.005)
    assert v == pytest.approx(car.max_accel * 0.005) and steer == pytest.approx(car.max_steer_rate * 0.005)
    radius = v / car.yaw_rate(v, 0.34)
    assert radius == pytest.approx(0.325 / math.tan(0.34))


def test_pure_pursuit_follows_a_straight_route_in_a_box():
    cfg = S.SimConfig(map="box", start=(-3.0, 0.5, 0.3), waypoints=((-2.0, 0.0), (3.0, 0.0)), speed=1.5)
    traj = S.simulate_trajectory(cfg, _box_map())
    assert traj.poses[-1, 0] == pytest.approx(3.0, abs=0.2)
    assert abs(traj.poses[-1, 1]) < 0.05  # converged onto the line
    assert np.all(np.abs(traj.v) <= 1.5 + 1e-9) and np.all(np.abs(traj.steer) <= 0.34 + 1e-12)
    assert traj.v[-1] < 0.05  # stopped at the end


def test_route_into_a_wall_is_a_collision():
    cfg = S.SimConfig(map="box", start=(0.0, 0.0, 0.0), waypoints=((1.0, 0.0), (6.0, 0.0)), speed=2.0)
    with pytest.raises(S.SimulationError, match="hits a wall"):
        S.simulate_trajectory(cfg, _box_map())


@pytest.mark.parametrize("name", sorted(SIM_TRIALS))
def test_every_trial_route_is_driven_without_touching_a_wall(name, stata):
    cfg = trial_config(name)
    traj = S.simulate_trajectory(cfg, stata)
    assert traj.min_clearance > cfg.car.radius + 0.1
    driven = float(np.sum(traj.v)) / S.PHYSICS_RATE_HZ
    duration = traj.t[-1]
    assert driven > 45.0
    assert 30.0 <= duration <= 80.0
    if name != "loop_noise0.3_biased":
        assert np.hypot(*(traj.poses[-1, :2] - np.asarray(cfg.waypoints[-1]))) < 0.3
    else:  # the loop passes its start again
        d = np.hypot(*(traj.poses[:, :2] - np.asarray(cfg.start[:2])).T)
        assert np.any(d[int(20 * S.PHYSICS_RATE_HZ):] < 0.5)


# ------------------------------------------------------------------ sensors


def test_odometry_noise_and_bias_statistics(stata):
    cfg = trial_config("trial1_noise0", duration=20.0, odom_noise=0.3, speed_scale=0.9, yaw_rate_bias=0.1)
    traj = S.simulate_trajectory(cfg, stata)
    odom = S.odometry_from_trajectory(traj, cfg, np.random.default_rng(0))
    assert np.diff(odom.t) == pytest.approx(0.02)
    err = odom.twist - odom.true_twist * np.array([0.9, 1.0, 1.0]) - np.array([0.0, 0.0, 0.1])
    assert err.std(axis=0) == pytest.approx([0.3, 0.3, 0.3], rel=0.1)
    assert np.abs(err.mean(axis=0)).max() < 0.05
    # true twist integrated over each period reproduces the true motion
    clean = S.odometry_from_trajectory(traj, replace(cfg, odom_noise=0.0, speed_scale=1.0, yaw_rate_bias=0.0),
                                       np.random.default_rng(0))
    steps = np.rint(clean.t * S.PHYSICS_RATE_HZ).astype(int)
    true_rel = relative(traj.poses[steps[0]], traj.poses[steps[-1]])
    assert clean.pose[-1] == pytest.approx(true_rel, abs=0.01)
    assert np.all(clean.twist[:, 1] == 0.0)


def test_lidar_ranges_are_ray_cast_plus_gaussian_noise(stata):
    cfg = trial_config("trial2_noise0.3")
    lidar = S.Lidar(stata, cfg, np.random.default_rng(1))
    assert lidar.angles.size == 1081
    assert lidar.angles[0] == pytest.approx(-2.356, abs=1e-3) and lidar.angles[-1] == pytest.approx(2.356, abs=1e-3)
    poses = np.array([cfg.start, [-12.0, 25.7, math.pi], [-30.0, 34.1, 0.1]])
    z = lidar.scan(poses)
    d = ExactRayCaster(stata, 10.0).cast(compose(poses, [0.275, 0.0, 0.0]), lidar.angles)
    inner = (d > 0.1) & (d < 9.9)
    diff = (z - d)[inner]
    assert diff.std() == pytest.approx(0.01, rel=0.15) and abs(diff.mean()) < 0.002
    assert z.max() <= 10.0 and z.min() >= 0.02


# ------------------------------------------------------------------ the bag


@pytest.fixture(scope="module")
def short_recording(tmp_path_factory, stata):
    cfg = trial_config("trial3_noise0.6", duration=4.0)
    path = tmp_path_factory.mktemp("sim") / "bag"
    rec = S.record(cfg, path, occupancy_map=stata)
    return rec, path


def test_bag_topics_rates_and_frames(short_recording):
    rec, path = short_recording
    info = bag_info(path)
    types = {k: v.msgtype for k, v in info.topics.items()}
    assert types == {"/scan": "sensor_msgs/msg/LaserScan", "/odom": "nav_msgs/msg/Odometry",
                     "/tf": "tf2_msgs/msg/TFMessage", "/tf_static": "tf2_msgs/msg/TFMessage",
                     "/initialpose": "geometry_msgs/msg/PoseWithCovarianceStamped"}
    assert info.topics["/tf_static"].latched
    assert info.topics["/scan"].count == 161 and info.topics["/odom"].count == 201  # 40 Hz, 50 Hz over 4 s
    scans = [m.msg for m in read_messages(path, ["/scan"])]
    s = scans[0]
    assert s.header.frame_id == "laser" and len(s.ranges) == 1081 and s.range_max == 10.0
    assert s.angle_min + 1080 * s.angle_increment == pytest.approx(s.angle_max, abs=1e-6)
    t = np.array([stamp_to_ns(m.header.stamp) for m in scans])
    assert np.all(np.diff(t) == 25_000_000)
    odoms = [m.msg for m in read_messages(path, ["/odom"])]
    assert odoms[0].header.frame_id == "odom" and odoms[0].child_frame_id == "base_link"
    assert np.all(np.diff([stamp_to_ns(m.header.stamp) for m in odoms]) == 20_000_000)
    static = next(iter(read_messages(path, ["/tf_static"]))).msg.transforms[0]
    assert (static.header.frame_id, static.child_frame_id) == ("base_link", "laser")
    assert static.transform.translation.x == pytest.approx(0.275)
    # bag time == header stamps, and messages come in time order
    for m in read_messages(path, ["/scan", "/odom"]):
        assert m.t_ns == stamp_to_ns(m.msg.header.stamp)


def test_bag_ground_truth_and_initial_pose(short_recording):
    rec, path = short_recording
    cfg = rec.cfg
    truth = []
    for m in read_messages(path, ["/tf"]):
        (tf,) = m.msg.transforms
        assert (tf.header.frame_id, tf.child_frame_id) == ("map", "base_link")
        tr = tf.transform.translation
        truth.append((stamp_to_sec(tf.header.stamp), tr.x, tr.y, yaw_of(tf.transform.rotation)))
    truth = np.array(truth)
    assert truth[0, 1:] == pytest.approx(cfg.start, abs=1e-9)
    steps = np.rint((truth[1:, 0] - truth[1, 0]) * S.PHYSICS_RATE_HZ).astype(int)
    assert truth[1:, 1:3] == pytest.approx(rec.trajectory.poses[steps, :2], abs=1e-6)
    # truth at every scan and odometry stamp
    stamps = {round(stamp_to_sec(m.msg.header.stamp), 6) for m in read_messages(path, ["/scan", "/odom"])}
    assert stamps <= {round(t, 6) for t in truth[:, 0]}
    (init,) = [m.msg for m in read_messages(path, ["/initialpose"])]
    p = init.pose.pose
    offset = np.array([p.position.x, p.position.y, yaw_of(p.orientation)]) - np.asarray(cfg.start)
    assert offset == pytest.approx(cfg.initial_offset, abs=1e-9)
    assert np.hypot(*offset[:2]) == pytest.approx(0.5) and offset[2] == pytest.approx(0.2)
    cov = np.asarray(init.pose.covariance).reshape(6, 6)
    assert cov[0, 0] == pytest.approx(0.25) and cov[5, 5] == pytest.approx(0.04)
    assert stamp_to_sec(init.header.stamp) < truth[1, 0]  # before the first sensor data


def test_odometry_pose_integrates_the_reported_twist(short_recording):
    rec, path = short_recording
    odoms = [m.msg for m in read_messages(path, ["/odom"])]
    pose = np.zeros(3)
    for prev, cur in zip(odoms[:-1], odoms[1:]):
        dt = (stamp_to_ns(cur.header.stamp) - stamp_to_ns(prev.header.stamp)) * 1e-9
        tw = cur.twist.twist
        pose = compose(pose, integrate_twist(tw.linear.x, tw.linear.y, tw.angular.z, dt))
    last = odoms[-1].pose.pose
    assert pose == pytest.approx([last.position.x, last.position.y, yaw_of(last.orientation)],
                                 abs=1e-6)


def test_deterministic_with_a_seed(stata):
    cfg = trial_config("trial2_noise0.3", duration=1.0)
    a, b = S.simulate(cfg, stata), S.simulate(cfg, stata)
    c = S.simulate(replace(cfg, seed=cfg.seed + 1), stata)
    assert np.array_equal(a.scan_ranges, b.scan_ranges) and np.array_equal(a.odometry.twist, b.odometry.twist)
    assert not np.array_equal(a.scan_ranges, c.scan_ranges)
    assert not np.array_equal(a.odometry.twist, c.odometry.twist)
    assert np.array_equal(a.trajectory.poses, c.trajectory.poses)  # the noise does not steer the car


def test_kidnapping_teleports_the_truth_but_not_the_odometry(stata):
    cfg = trial_config("trial1_noise0", duration=6.0, kidnap_at=3.0, kidnap_to=(-35.0, -0.4, 3.1))
    rec = S.simulate(cfg, stata)
    k = rec.trajectory.kidnapped_at_step
    assert k == 3 * S.PHYSICS_RATE_HZ
    jump = np.hypot(*np.diff(rec.trajectory.poses[:, :2], axis=0).T)
    assert jump.argmax() == k - 1 and jump.max() > 10.0
    assert np.sort(jump)[-2] < 0.05  # no other jump
    assert rec.trajectory.poses[k] == pytest.approx([-35.0, -0.4, 3.1])
    assert rec.trajectory.poses[-1, 0] < -37.0  # drives on west along the route
    odom_step = np.hypot(*np.diff(rec.odometry.pose[:, :2], axis=0).T)
    assert odom_step.max() < 0.05


def test_mcap_storage(tmp_path, stata):
    rec = S.record(trial_config("trial1_noise0", duration=0.5), tmp_path / "m", storage="mcap", occupancy_map=stata)
    info = bag_info(tmp_path / "m")
    assert info.topics["/scan"].count == len(rec.scan_t) == 21


# ------------------------------------------------------------------ command line and cache


def test_cli_records_a_bag(tmp_path, capsys):
    out = tmp_path / "cli"
    assert simulate_cli.main([str(out), "--trial", "trial2_noise0.3", "--duration", "1", "--odom-noise", "0.6",
                   "--no-initialpose", "--storage", "mcap"]) == 0
    assert "wrote" in capsys.readouterr().out
    info = bag_info(out)
    assert "/initialpose" not in info.topics and info.topics["/odom"].count == 51
    # exists already
    assert simulate_cli.main([str(out), "--trial", "trial2_noise0.3", "--duration", "1"]) == 1
    assert "exists" in capsys.readouterr().err
    assert simulate_cli.main([str(out), "--trial", "trial2_noise0.3", "--duration", "1", "--overwrite"]) == 0


@pytest.mark.parametrize("argv, message", [
    (["--trial", "trial1_noise0", "--kidnap-at", "3"], "go together"),
    ([], "no route"),
    (["--waypoints", "0,0;1,1", "--start", "500,500,0"], "not in free space"),
    (["--trial", "trial1_noise0", "--speed", "9"], "--speed"),
])
def test_cli_errors_are_one_clear_line(tmp_path, capsys, argv, message):
    assert simulate_cli.main([str(tmp_path / "x"), *argv]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("localization-simulate: error:") and message in err and "\n" not in err


def test_custom_waypoints_from_the_command_line(tmp_path, capsys):
    wp = tmp_path / "route.txt"
    wp.write_text("# x y\n-8.45 18.4\n-10.4 16.3\n")
    assert simulate_cli.main([str(tmp_path / "b"), "--start=-6.6,20.5,-2.24", "--waypoints", str(wp)]) == 0
    assert bag_info(tmp_path / "b").topics["/scan"].count > 40


def test_sim_bag_is_cached_by_config(tmp_path, monkeypatch):
    calls = []
    real_record = S.record

    def counting_record(*a, **k):
        calls.append(a[0])
        return real_record(*a, **k)

    monkeypatch.setattr(datasets, "record", counting_record)
    a = sim_bag("trial1_noise0", cache=tmp_path, duration=0.5)
    b = sim_bag("trial1_noise0", cache=tmp_path, duration=0.5)
    c = sim_bag("trial1_noise0", cache=tmp_path, duration=0.6)
    assert a == b != c and len(calls) == 2
    assert (a / "metadata.yaml").is_file() and (a.parent / "config.json").is_file()
    assert not list(tmp_path.glob("sim/*.tmp-*"))


def test_real_bag_table_points_at_the_shared_bags(shared_dir):
    for name, rb in REAL_BAGS.items():
        assert real_bag_path(name).is_file(), name
        assert rb.map == "basement_fixed"
