"""End-to-end tests of the particle_filter node over DDS (loopback only, see conftest.py).

The node runs in this process (own rclpy Context, SingleThreadedExecutor in a background thread, as main() spins it)
or as a subprocess; a probe node publishes a map, an initial pose and a recorded sequence of
odometry and scans, in lock step (each message is published once the node handled the previous
one), and records /pf/pose/odom, /pf/particles and /tf.
"""
from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("tf2_msgs.msg", reason="tf2_msgs not built into this venv (scripts/build_tf2_msgs.sh)")

import node_harness as h  # noqa: E402
import rclpy  # noqa: E402
from geometry_msgs.msg import PoseArray  # noqa: E402
from helpers import wrap_sensor_updates  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402

from localization.core.geometry import compose, quaternion_to_yaw, wrap_angle  # noqa: E402
from localization.core.localizer import Localizer  # noqa: E402
from localization.core.occupancy_map import OccupancyMap  # noqa: E402
from localization.core.parameters import Parameters  # noqa: E402
from localization.ros.conversions import pose_from_msg, pose_from_pose_with_covariance  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "config"




def tf_pose(t):
    q = t.transform.rotation
    return np.array([t.transform.translation.x, t.transform.translation.y,
                     float(quaternion_to_yaw(q.x, q.y, q.z, q.w))])


def odom_pose(msg: Odometry):
    return pose_from_msg(msg.pose.pose)


def particles_array(msg: PoseArray):
    return np.array([[p.position.x, p.position.y, float(quaternion_to_yaw(p.orientation.x, p.orientation.y,
                                                                            p.orientation.z, p.orientation.w))]
                     for p in msg.poses])


def all_finite_odometry(msg: Odometry):
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    return np.all(np.isfinite([p.x, p.y, p.z, q.x, q.y, q.z, q.w, *msg.pose.covariance]))


def start_localizing(r, drive, pose=None):
    r.send_map(h.map_msg("stata_basement"))
    r.send_initialpose(h.initialpose_msg(drive.initial_guess if pose is None else pose))


# ------------------------------------------------------------------------------------------ e2e
def test_synthetic_drive_converges_with_right_frames_and_stamps(runner, drive):
    r = runner()
    start_localizing(r, drive)
    r.play(drive.events)
    r.settle()
    poses, particles, tfs = r.probe.snapshot()

    odom_keys = {h.ns_key(t) for t, kind, _ in drive.events if kind == "odom"}
    scan_keys = {h.ns_key(t) for t, kind, _ in drive.events if kind == "scan"}
    init_key = h.ns_key(h.T0_NS)

    # /pf/pose/odom: frames, exact input stamps, one per odometry message, no NaN
    assert len(poses) >= len(odom_keys) - 1
    assert all(m.header.frame_id == "map" and m.child_frame_id == "base_link_pf" for m in poses)
    assert all(h.key(m.header.stamp) in odom_keys | scan_keys for m in poses)
    assert odom_keys - {h.key(m.header.stamp) for m in poses} <= {min(odom_keys)}  # the first only sets dt
    assert h.key(poses[-1].header.stamp) == h.ns_key(drive.events[-1][0])
    assert all(all_finite_odometry(m) for m in poses)

    # /pf/particles: frame map, capped, stamped with the scan (or the initial pose) they reflect
    assert len(particles) >= 10
    assert all(m.header.frame_id == "map" for m in particles)
    assert all(h.key(m.header.stamp) in scan_keys | {init_key} for m in particles)
    assert {len(m.poses) for m in particles} == {200}  # max_particles_published caps 500 particles
    assert np.all(np.isfinite(particles_array(particles[-1])))

    # /tf: map -> base_link_pf, stamps strictly increasing, equal to the pose published with that stamp
    assert len(tfs) >= len(odom_keys) - 1
    assert all(t.header.frame_id == "map" and t.child_frame_id == "base_link_pf" for t in tfs)
    stamps = [h.stamp_sec(t.header.stamp) for t in tfs]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    by_stamp = {h.key(m.header.stamp): odom_pose(m) for m in poses}
    for t in tfs[-20:]:
        np.testing.assert_allclose(tf_pose(t), by_stamp[h.key(t.header.stamp)], atol=1e-9)

    # convergence: the last estimate is within 0.15 m (and a few degrees) of the truth
    final_t = drive.events[-1][0]
    est, truth = odom_pose(poses[-1]), drive.truth(final_t)
    assert np.hypot(*(est[:2] - truth[:2])) < 0.15, (est, truth)
    assert abs(wrap_angle(est[2] - truth[2])) < 0.1
    # ... from a cloud that started 0.32 m off (the first cloud is the one for /initialpose)
    assert h.key(particles[0].header.stamp) == init_key
    assert np.hypot(*(particles_array(particles[0])[:, :2].mean(axis=0) - drive.start[:2])) > 0.25
    # the reported covariance is small and finite
    cov = np.array(poses[-1].pose.covariance).reshape(6, 6)
    assert 0 < cov[0, 0] < 0.05 and 0 < cov[1, 1] < 0.05


def test_no_output_before_map_and_initial_pose(runner, drive, capfd):
    r = runner()
    early = drive.until(0.3)
    r.play(early)  # no map, no pose
    r.settle(0.2)
    assert r.probe.snapshot() == ([], [], [])
    assert r.node.counts["odom"] > 0 and r.node.counts["scan"] > 0  # they were delivered, and ignored
    log = capfd.readouterr().err.splitlines()
    # one line per kind of input, however many messages (throttled)
    assert len([line for line in log if "odometry" in line and "no map" in line]) == 1, log
    assert len([line for line in log if "scan" in line and "no map" in line]) == 1, log

    r.send_map(h.map_msg("stata_basement"))
    r.play(early)  # a map but no initial pose
    r.settle(0.2)
    assert r.probe.snapshot() == ([], [], [])

    r.send_initialpose(h.initialpose_msg(drive.initial_guess))
    assert h.wait_until(lambda: len(r.probe.snapshot()[1]) == 1, 5.0)  # the new cloud is shown at once
    r.play(drive.until(0.5))
    r.settle(0.2)
    poses, particles, tfs = r.probe.snapshot()
    assert poses and tfs and len(particles) > 1


def test_global_localization_parameter_spreads_particles_once_a_map_arrives(runner):
    r = runner(global_localization=True)
    r.send_map(h.map_msg("stata_basement"))
    assert h.wait_until(lambda: len(r.probe.snapshot()[1]) >= 1, 5.0)
    cloud = particles_array(r.probe.snapshot()[1][-1])
    assert cloud[:, 0].std() > 3.0 and cloud[:, 1].std() > 3.0  # spread over the whole basement
    assert r.node.localizer.ready


def test_new_initialpose_reinitialises_the_cloud(runner, drive):
    r = runner()
    start_localizing(r, drive)
    r.play(drive.until(1.0))
    r.settle(0.2)
    elsewhere = np.array([-3.0, 24.0, 0.9])  # another free spot of the basement, 5 m away
    assert h.load_map("stata_basement").is_free(elsewhere[None, :2])[0]

    r.probe.clear()
    r.send_initialpose(h.initialpose_msg(elsewhere, t_ns=h.T0_NS + 1_010_000_000, frame_id="odom"))
    r.settle(0.2)
    assert r.probe.snapshot()[1] == []  # wrong frame: ignored, no new cloud
    assert np.hypot(*(r.node.localizer.estimate.pose[:2] - elsewhere[:2])) > 3.0

    r.send_initialpose(h.initialpose_msg(elsewhere, t_ns=h.T0_NS + 1_010_000_000, std=(0.2, 0.2, 0.05)))
    assert h.wait_until(lambda: len(r.probe.snapshot()[1]) == 1, 5.0)
    cloud_msg = r.probe.snapshot()[1][0]
    assert h.key(cloud_msg.header.stamp) == h.ns_key(h.T0_NS + 1_010_000_000)
    cloud = particles_array(cloud_msg)
    assert np.hypot(*(cloud[:, :2].mean(axis=0) - elsewhere[:2])) < 0.1
    assert 0.1 < cloud[:, 0].std() < 0.35
    # the next odometry message publishes a pose at the new place
    t = h.T0_NS + 1_020_000_000
    r.send_odom(h.odom_msg(t, (0.0, 0.0, 0.0), 0.0))
    assert h.wait_until(lambda: any(h.key(m.header.stamp) == h.ns_key(t) for m in r.probe.snapshot()[0]), 5.0)
    pose = odom_pose(r.probe.snapshot()[0][-1])
    assert np.hypot(*(pose[:2] - elsewhere[:2])) < 0.1 and abs(wrap_angle(pose[2] - elsewhere[2])) < 0.05


def test_second_map_replaces_the_first(runner, drive):
    r = runner()
    start_localizing(r, drive)
    r.play(drive.until(0.5))
    before = r.node.localizer.estimate.pose.copy()

    # the same map again: the particles (all in free space) are kept
    r.send_map(h.map_msg("stata_basement"))
    np.testing.assert_allclose(r.node.localizer.estimate.pose, before)
    assert r.node.localizer.ready

    # another map that also has free space where the car is: it is used, the particles are kept
    other = h.load_map("building_31")
    r.send_map(h.map_msg("building_31"))
    np.testing.assert_array_equal(r.node.localizer.map.data, other.data)
    assert r.node.localizer.ready
    r.settle(0.2)
    r.probe.clear()
    r.play(drive.until(0.7)[-5:])
    r.settle(0.2)
    poses = r.probe.snapshot()[0]
    assert poses and all(all_finite_odometry(m) for m in poses)

    # a map placed 100 m away: no particle is in its free space any more; outputs stop until a new pose
    far = h.OccupancyMap(other.data, other.resolution, (other.origin[0] + 100.0, other.origin[1], other.origin[2]))
    r.send_map(h.occupancy_grid_msg(far))
    assert not r.node.localizer.ready
    r.settle(0.2)
    r.probe.clear()
    r.play(drive.until(1.0)[-10:])
    r.settle(0.2)
    assert r.probe.snapshot() == ([], [], [])

    # a pose in the new map: outputs resume, inside the new map's free space
    free_xy = far.grid_to_world(far.free_cells[len(far.free_cells) // 2][::-1])
    r.send_initialpose(h.initialpose_msg((free_xy[0], free_xy[1], 0.0), t_ns=h.T0_NS + 995_000_000,
                                         std=(0.05, 0.05, 0.02)))
    t = h.T0_NS + 1_003_000_000  # the next odometry message (20 ms after the last one)
    r.send_odom(h.odom_msg(t, (0.0, 0.0, 0.0), 0.0))
    assert h.wait_until(lambda: len(r.probe.snapshot()[0]) >= 1, 5.0)
    pose = odom_pose(r.probe.snapshot()[0][-1])
    assert np.hypot(*(pose[:2] - free_xy)) < 0.1


def test_map_to_odom_tf_composes_with_odometry_to_the_estimate(runner, drive):
    r = runner(publish_tf="map_to_odom")
    start_localizing(r, drive)
    events = drive.until(1.0)
    r.play(events)
    r.settle()
    poses, _, tfs = r.probe.snapshot()
    odom_at = {h.ns_key(t): odom_pose(m) for t, kind, m in events if kind == "odom"}
    est_at = {h.key(m.header.stamp): odom_pose(m) for m in poses}
    assert len(tfs) > 30
    assert all(t.header.frame_id == "map" and t.child_frame_id == "odom" for t in tfs)
    assert all(m.child_frame_id == "base_link_pf" for m in poses)
    checked = 0
    for t in tfs:
        k = h.key(t.header.stamp)
        if k in odom_at:  # map -> odom ⊕ odom -> base_link == map -> base_link (the estimate)
            np.testing.assert_allclose(compose(tf_pose(t), odom_at[k]), est_at[k], atol=1e-6)
            checked += 1
    assert checked > 30
    # odometry starts at 0 at the start pose: map -> odom stays near the start pose (the 5 % short
    # odometry shifts it a little), and map -> odom ⊕ odom -> base_link tracks the truth
    last = tfs[-1]
    assert np.hypot(*(tf_pose(last)[:2] - drive.start[:2])) < 0.3
    truth = drive.truth(events[-1][0])
    assert np.hypot(*(compose(tf_pose(last), list(odom_at.values())[-1])[:2] - truth[:2])) < 0.15


def block_sensor_updates(r, drive):
    """Start localizing, then make every sensor update wait for ``release``; ``entered`` is set when
    one starts. Returns (entered, release, odometry events, scan events) of the drive's first second."""
    start_localizing(r, drive)
    entered, release = threading.Event(), threading.Event()
    pf = r.node.localizer._pf

    def slow(original):
        def slow_update(*args, **kwargs):
            entered.set()
            release.wait(10.0)
            return original(*args, **kwargs)
        return slow_update

    wrap_sensor_updates(pf, slow)
    events = drive.until(1.0)
    return entered, release, [e for e in events if e[1] == "odom"], [e for e in events if e[1] == "scan"]


@pytest.mark.parametrize("overrides", [{"sensor_update_thread": True}], ids=["thread"])
def test_slow_sensor_update_does_not_block_pose_on_odometry(runner, drive, overrides):
    """With ``sensor_update_thread`` odometry poses keep flowing during a (blocked) sensor update."""
    r = runner(**overrides)
    assert r.node.scan_worker is not None
    entered, release, odoms, scans = block_sensor_updates(r, drive)
    try:
        for _, _, msg in odoms[:3]:  # odometry up to the scan's time: the scan is used when it arrives
            r.send_odom(msg)
        r.probe.scan_pub.publish(scans[1][2])  # not waited for: its update blocks
        assert entered.wait(5.0)
        for _, _, msg in odoms[3:13]:
            r.send_odom(msg)  # each is handled (and its pose published) during the sensor update
        want = {h.ns_key(t) for t, _, _ in odoms[3:13]}
        assert h.wait_until(lambda: want <= {h.key(m.header.stamp) for m in r.probe.snapshot()[0]}, 5.0)
        assert r.node.counts["scan"] == 0  # the sensor update is still running
        moving = [odom_pose(m) for m in r.probe.snapshot()[0] if h.key(m.header.stamp) in want]
        assert moving[-1][0] != moving[0][0]  # the queued odometry moves the published estimate
    finally:
        release.set()
    assert h.wait_until(lambda: r.node.counts["scan"] == 1, 10.0)
    assert h.wait_until(lambda: any(h.key(m.header.stamp) == h.ns_key(scans[1][0]) for m in r.probe.snapshot()[1]),
                        5.0)
    # the odometry queued during the update is applied before the next scan: nothing is lost
    r.send_odom(odoms[13][2])
    assert h.wait_until(lambda: h.key(r.probe.snapshot()[0][-1].header.stamp) == h.ns_key(odoms[13][0]), 5.0)
    travelled = np.hypot(*(odom_pose(r.probe.snapshot()[0][-1])[:2] - drive.initial_guess[:2]))
    assert travelled > 0.8 * 2.0 * 0.95 * (odoms[13][0] - odoms[0][0]) * 1e-9


def test_a_scan_waiting_for_odometry_is_run_when_the_odometry_arrives(runner, drive):
    """On the sensor-update thread, a scan newer than the odometry is run as soon as the odometry reaches its
    time (the odometry callback pokes the thread), not at the next scan."""
    r = runner(sensor_update_thread=True)
    start_localizing(r, drive)
    events = drive.until(1.0)
    odoms, scans = [e for e in events if e[1] == "odom"], [e for e in events if e[1] == "scan"]
    scan_t, _, scan = scans[1]  # 25 ms: the odometry before it is at 23 ms, the next at 43 ms
    for t, _, msg in odoms:
        if t < scan_t:
            r.send_odom(msg)
    r.send_scan(scan)
    assert h.wait_until(lambda: r.node.localizer.waiting_scans == 1, 5.0)
    r.settle(0.2)
    assert not r.probe.corrections_snapshot()  # it waits for odometry past its time
    r.send_odom(next(msg for t, _, msg in odoms if t > scan_t))
    assert h.wait_until(lambda: any(h.key(m.header.stamp) == h.ns_key(scan_t) for m in r.probe.corrections_snapshot()),
                        5.0)
    assert r.node.localizer.waiting_scans == 0


def test_the_laser_pose_decided_on_the_sensor_update_thread_leaves_subscriptions_to_the_executor(runner, drive):
    """Without TF the first scan (on the sensor-update thread) falls back to the laser_offset_* parameters and stops
    listening to /tf; the subscription is destroyed on the executor's thread (destroying it on another thread while
    the executor waits on it raised in the executor and ended the node), and the node goes on localizing."""
    r = runner(tf_timeout=0.01, diagnostics_period=0.1)
    lookup = r.node.laser.lookup
    assert lookup is not None and len(lookup._subs) == 2  # /tf_static and /tf
    destroyed_on = []
    destroy = r.node.destroy_subscription

    def recording_destroy(sub):
        destroyed_on.append(threading.current_thread())
        return destroy(sub)
    r.node.destroy_subscription = recording_destroy
    start_localizing(r, drive)
    r.play(drive.until(0.5))
    assert h.wait_until(lambda: r.node.laser.source == "parameters" and len(lookup._subs) == 1, 5.0)
    assert destroyed_on == [r.thread]  # the executor's thread, not the sensor update's
    before = r.node.counts["scan"]
    r.play([e for e in drive.events if 0.5e9 < e[0] - h.T0_NS <= 1.0e9])
    assert r.node.counts["scan"] > before and r.thread.is_alive()


def test_sensor_update_in_the_callback_loses_no_odometry(runner, drive):
    """With ``sensor_update_thread`` false the scan callback runs the sensor update: odometry arriving
    meanwhile waits in its queue and is handled, in order and completely, right after the update."""
    r = runner(sensor_update_thread=False)
    assert r.node.scan_worker is None
    entered, release, odoms, scans = block_sensor_updates(r, drive)
    for _, _, msg in odoms[:3]:  # odometry up to the scan's time: the scan is used when it arrives
        r.send_odom(msg)
    r.probe.scan_pub.publish(scans[1][2])
    assert entered.wait(5.0)
    for _, _, msg in odoms[3:13]:
        r.probe.odom_pub.publish(msg)  # queued behind the running sensor update
    time.sleep(0.3)
    want = [h.ns_key(t) for t, _, _ in odoms[3:13]]
    assert not set(want) & {h.key(m.header.stamp) for m in r.probe.snapshot()[0]}  # still blocked
    release.set()
    assert h.wait_until(lambda: r.node.counts["scan"] == 1, 10.0)
    assert h.wait_until(lambda: set(want) <= {h.key(m.header.stamp) for m in r.probe.snapshot()[0]}, 5.0)
    got = [h.key(m.header.stamp) for m in r.probe.snapshot()[0] if h.key(m.header.stamp) in set(want)]
    assert got == want  # every one, in order
    travelled = np.hypot(*(odom_pose(r.probe.snapshot()[0][-1])[:2] - drive.initial_guess[:2]))
    assert travelled > 0.8 * 2.0 * 0.95 * (odoms[12][0] - odoms[0][0]) * 1e-9


def run_seeded(runner, drive, seed, seconds=1.0):
    r = runner(random_seed=seed, max_particles_published=500)
    start_localizing(r, drive)
    r.play(drive.until(seconds))
    r.settle(0.2)
    poses, particles, _ = r.probe.snapshot()
    out = (np.array([odom_pose(m) for m in poses]), particles_array(particles[-1]), r.node.localizer.particles())
    r.close()
    return out


def test_reproducible_with_a_seed(runner, drive):
    poses_a, cloud_a, internal_a = run_seeded(runner, drive, 7)
    poses_b, cloud_b, internal_b = run_seeded(runner, drive, 7)
    _, cloud_c, _ = run_seeded(runner, drive, 8)
    assert len(poses_a) > 40
    np.testing.assert_array_equal(internal_a, internal_b)
    np.testing.assert_array_equal(poses_a, poses_b)
    np.testing.assert_array_equal(cloud_a, cloud_b)
    assert not np.array_equal(cloud_a, cloud_c)  # the seed matters


def test_reinitialize_global_localization_service(runner):
    from std_srvs.srv import Empty

    r = runner()
    r.send_map(h.map_msg("stata_basement"))
    assert not r.node.localizer.ready
    assert r.probe.reinit_client.wait_for_service(timeout_sec=5.0)
    future = r.probe.reinit_client.call_async(Empty.Request())
    assert h.wait_until(future.done, 5.0)
    assert r.node.localizer.ready
    assert h.wait_until(lambda: len(r.probe.snapshot()[1]) == 1, 5.0)
    cloud = r.node.localizer.particles()
    assert cloud[:, 0].std() > 3.0 and cloud[:, 1].std() > 3.0
    m = h.load_map("stata_basement")
    assert m.is_free(cloud[:, :2]).mean() > 0.99


# ------------------------------------------------------------------------------------------ real bag
def test_real_bag_through_the_node_matches_the_core(runner, shared_dir):
    """The real racecar bag (ROS 1, replayed as CDR) on basement_fixed: the node's estimates are
    exactly those of the ROS-free core fed the same messages, and end in the diagonal corridor."""
    from nav_msgs.msg import OccupancyGrid
    from nav_msgs.msg import Odometry as OdometryMsg
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import LaserScan

    from localization.bags import read_messages
    from localization.ros.conversions import scan_from_msg, twist_from_odometry

    bag = shared_dir / "bags" / "rss2022" / "localization_bag3.bag"
    if not bag.exists():
        pytest.skip(f"real bag not available: {bag}")
    params = Parameters.from_yaml(CONFIG / "real_params.yaml", **h.TEST_PARAMS, odom_topic="/odom")
    msgs = [(m.topic, m.msg, m.raw_cdr) for m in read_messages(bag, ["/scan", "/vesc/odom"])]
    initialpose = h.initialpose_msg((1.3, 0.2, 1.59), t_ns=0, std=(0.3, 0.3, 0.1))

    # the core alone
    core = Localizer(params)
    # the map as the node receives it: resolution is a float32 on the wire
    core.set_map(OccupancyMap.from_msg(deserialize_message(serialize_message(h.map_msg("basement_fixed")),
                                                           OccupancyGrid)))
    init = pose_from_pose_with_covariance(initialpose)
    core.set_initial_pose(init.pose, init.covariance, 0.0)
    for topic, msg, _ in msgs:
        if topic == "/scan":
            s = scan_from_msg(msg)
            core.on_scan(s)
        else:
            tw = twist_from_odometry(msg)
            core.on_odometry(tw)

    # the node, fed the recorded CDR bytes over DDS
    r = runner(**params)
    r.send_map(h.map_msg("basement_fixed"))
    r.send_initialpose(initialpose)
    for topic, _, raw in msgs:
        if topic == "/scan":
            r.send_scan(deserialize_message(raw, LaserScan))
        else:
            r.send_odom(deserialize_message(raw, OdometryMsg))
    r.settle(0.2)
    poses = r.probe.snapshot()[0]
    assert all(m.header.frame_id == "map" and all_finite_odometry(m) for m in poses)
    final = odom_pose(poses[-1])
    np.testing.assert_allclose(final, core.estimate.pose, atol=1e-9)
    # it ends where the last scan fits the map (the diagonal corridor)
    from localization.eval.feed import make_scorer
    last = scan_from_msg(next(m for t, m, _ in reversed(msgs) if t == "/scan"))
    pose = core.estimate_at(core.scan_time(last)).pose
    agreement = make_scorer(core.map, params).score(pose, last.ranges, _angles(last), last.range_min, last.range_max)
    assert agreement > 0.8, (pose, agreement)


def _angles(scan):
    from localization.core.scan import beam_angles
    return beam_angles(np.size(scan.ranges), scan.angle_min, scan.angle_max, scan.angle_increment)


# ------------------------------------------------------------------------------------------ files
@pytest.mark.parametrize("name", ["params.yaml"])  # robot files hold only their own values (test_parameter_surface)
def test_parameter_files_name_only_declared_parameters(name):
    import yaml

    from localization.core.parameters import BY_NAME

    section = yaml.safe_load((CONFIG / name).read_text())["particle_filter"]["ros__parameters"]
    assert set(section) <= set(BY_NAME), set(section) - set(BY_NAME)
    course = {"num_particles", "num_beams_per_particle", "scan_field_of_view", "scan_theta_discretization",
              "map_topic", "scan_topic", "odom_topic", "particle_filter_frame", "deterministic",
              "lidar_scale_to_map_scale"}
    ours = {"alpha_hit", "alpha_short", "alpha_max", "alpha_rand", "sigma_hit", "squash_factor", "motion_a_trans",
            "motion_a_lateral", "motion_a_rot", "motion_a_rot_to_trans", "motion_a_trans_to_rot", "laser_offset_x",
            "laser_offset_y", "laser_offset_yaw", "random_seed", "publish_tf", "max_particles_published"}
    assert course | ours <= set(section), (course | ours) - set(section)
    Parameters.from_yaml(CONFIG / name)  # valid


def test_launch_file_starts_the_node_with_params_yaml():
    import ast

    source = (REPO / "launch" / "particle_filter.launch.py").read_text()
    ast.parse(source)
    assert '"params.yaml"' in source and 'executable="particle_filter"' in source
    assert "<exec_depend>launch_ros</exec_depend>" in (REPO / "package.xml").read_text()


# ------------------------------------------------------------------------------------------ subprocesses
def _run_node(*ros_args, timeout=20.0):
    return subprocess.run([sys.executable, "-m", "localization.particle_filter", "--ros-args", *ros_args],
                          capture_output=True, text=True, timeout=timeout, cwd=REPO)


def test_bad_parameter_values_are_refused_at_start():
    proc = _run_node("-p", "num_particles:=0", "-p", "publish_tf:=map_to_nowhere", "-p", "sigma_hit:=-1.0")
    out = proc.stdout + proc.stderr
    assert proc.returncode != 0
    assert "invalid parameters" in out
    assert "num_particles=0 must be an integer in [1, 1000000]" in out
    assert "publish_tf='map_to_nowhere'" in out and "sigma_hit=-1.0 must be > 0" in out


def test_bad_parameter_type_is_refused_and_int_for_float_is_accepted():
    proc = _run_node("-p", "num_particles:=many")
    assert proc.returncode != 0
    assert "num_particles='many' must be an integer" in proc.stdout + proc.stderr
    # an integer where a float is expected is fine (`laser_offset_x:=0`): the node starts
    proc = subprocess.Popen([sys.executable, "-m", "localization.particle_filter", "--ros-args",
                             "-p", "laser_offset_x:=0", "-p", "random_seed:=3"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO)
    lines = []
    try:
        deadline = time.monotonic() + 60.0  # the imports alone take seconds on a loaded machine
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            lines.append(line)
            if not line or "particle filter ready" in line:
                break
        assert proc.poll() is None, "".join(lines) + proc.communicate()[0]
    finally:
        proc.send_signal(signal.SIGINT)
        out = "".join(lines) + proc.communicate(timeout=10)[0]
    assert proc.returncode == 0, out
    assert "particle filter ready" in out


def test_console_script_with_the_parameter_file(context, drive):
    """`particle_filter --ros-args --params-file config/params.yaml` (what `ros2 run` starts):
    localizes from DDS input and exits cleanly on Ctrl-C."""
    script = Path(sys.executable).parent / "particle_filter"
    cmd = [str(script)] if script.exists() else [sys.executable, "-m", "localization.particle_filter"]
    proc = subprocess.Popen(cmd + ["--ros-args", "--params-file", str(CONFIG / "params.yaml"),
                                   "-p", "num_particles:=300", "-p", "ray_caster:=distance_transform"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO)
    probe = h.Probe(context, name="pf_test_probe_subprocess")
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(probe)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    try:
        probe.wait_connected(timeout=20.0)
        probe.map_pub.publish(h.map_msg("stata_basement"))
        # the node shows the cloud for an initial pose once it has the map: repeat until it does
        deadline = time.monotonic() + 20.0
        while not probe.snapshot()[1] and time.monotonic() < deadline and proc.poll() is None:
            probe.initialpose_pub.publish(h.initialpose_msg(drive.initial_guess))
            h.wait_until(lambda: bool(probe.snapshot()[1]), 0.5)
        assert probe.snapshot()[1], "no particle cloud for the initial pose"
        for _, kind, msg in drive.until(0.5):
            (probe.odom_pub if kind == "odom" else probe.scan_pub).publish(msg)
            time.sleep(0.02)
        assert h.wait_until(lambda: len(probe.snapshot()[0]) >= 10 and probe.snapshot()[2], 10.0)
        poses, particles, tfs = probe.snapshot()
        assert poses[-1].header.frame_id == "map" and poses[-1].child_frame_id == "base_link_pf"
        assert tfs[-1].child_frame_id == "base_link_pf"
        # the node may still be working through the stream: judge the last pose against the truth
        # at the time it reflects (its stamp), not at the end of the stream
        last = poses[-1]
        t_ns = last.header.stamp.sec * 1_000_000_000 + last.header.stamp.nanosec
        assert h.T0_NS < t_ns <= h.T0_NS + 500_000_000
        assert np.hypot(*(odom_pose(last)[:2] - drive.truth(t_ns)[:2])) < 0.5
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        out = proc.communicate(timeout=10)[0]
        executor.shutdown(timeout_sec=5.0)
        spinner.join(timeout=5.0)
        probe.destroy_node()
    assert proc.returncode == 0, out
    assert "2000 particles" not in out and "300 particles" in out


def test_node_callbacks_benchmark_feeds_the_whole_bag(shared_dir):
    """``benchmarks.node_callbacks``: RSS bag1's bytes through the node's callbacks; the core's part of each
    callback's CPU is inside that callback's."""
    from localization.benchmarks.node_callbacks import measure
    if not (shared_dir / "bags" / "rss2022").exists():
        pytest.skip("the RSS bags are not available")
    r = measure("bag1", repeat=1)
    assert r["scans"] == 281  # every scan of bag1 handled
    for kind in ("odometry", "scan"):
        assert 0.0 < r["core_percent"][kind] <= r["by_callback_percent"][kind]
    assert r["share_percent"] == pytest.approx(sum(r["by_callback_percent"].values()))
