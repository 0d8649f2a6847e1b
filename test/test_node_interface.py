"""The node's interface for a car and a nav2 user, over DDS with a live node:
/diagnostics and watchdogs, initial pose from parameters, laser pose from /tf_static, the
lifecycle variant, pose persistence, request_nomotion_update, the cold start with an empty range
table cache, and the command line (--help, a missing parameter file, a clean Ctrl-C).
The ROS-free watchdog logic is tested with a fake clock first."""
from __future__ import annotations

import math
import os
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
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import PoseWithCovarianceStamped, TransformStamped  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from std_srvs.srv import Empty  # noqa: E402
from tf2_msgs.msg import TFMessage  # noqa: E402

from localization.core import pose_store  # noqa: E402
from localization.core.geometry import yaw_to_quaternion  # noqa: E402
from localization.core.localizer.recovery import TRACKING  # noqa: E402
from localization.core.watchdog import ERROR, OK, WARN, ProblemLog, Watchdog  # noqa: E402
from localization.ros.conversions import pose_from_msg  # noqa: E402
from localization.ros.messages import diagnostic_array_msg  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------ ROS-free watchdog
def test_watchdog_warns_for_missing_odometry_naming_the_topics():
    w = Watchdog(0.0, odom_timeout=0.5, scan_timeout=0.5, map_timeout=5.0, odom_topic="/odom")
    w.map_building(0.1)
    w.map_ready(0.2)
    for k in range(10):
        w.scan_received(0.3 + 0.025 * k)
    st = w.status(0.6, ready=True, odom_topics=["/vesc/odom"])
    assert st.level == OK  # 0.3 s after the first scan: not yet
    w.scan_received(0.9)
    st = w.status(0.9, ready=True, odom_topics=["/vesc/odom", "/odom"])
    assert st.level == WARN and "/odom" in st.message and "/vesc/odom" in st.message
    assert st.problems[0].key == "no-odom"
    # odometry comes: the warning clears
    w.odom_received(0.95)
    assert w.status(1.0, ready=True).level == OK


def test_watchdog_missing_scans_map_tf_and_failures():
    w = Watchdog(0.0, odom_timeout=0.5, scan_timeout=0.5, map_timeout=2.0, tf_timeout=1.0)
    assert w.status(0.2, ready=False).level == OK  # just started
    assert {p.key for p in w.problems(1.0)} == {"no-input"}
    assert "no-map" in {p.key for p in w.problems(2.5)}
    for k in range(30):
        w.odom_received(3.0 + 0.02 * k)
    assert "no-scan" in {p.key for p in w.problems(3.6)}
    w.tf_failed(3.0, "base_link -> laser: no chain")
    assert "tf" in {p.key for p in w.problems(4.1)}
    w.map_failed(4.2, "bad table")
    st = w.status(4.2, ready=False, waiting_for="a map")
    assert st.level == ERROR and "bad table" in st.message
    assert st.values["state"] == "waiting for a map"


def test_watchdog_rates_and_latency_and_problem_log():
    w = Watchdog(0.0)
    w.map_ready(0.0)
    for k in range(100):
        w.scan_received(k * 0.025)
        w.odom_received(k * 0.025)
        w.scan_processed(k * 0.025, True, {"wait": 0.001, "convert": 0.0005, "update": 0.004, "publish": 0.001})
    lat = w.latency(2.5)
    assert abs(lat["total"][0] - 0.0065) < 1e-9 and abs(lat["update"][1] - 0.004) < 1e-9
    assert abs(w.update_rate(2.5) - 100 / 2.5) < 1.0
    st = w.status(2.5, ready=True, particles=4000, dropped=2, health=0.9)
    assert st.values["scan to pose latency p95 (ms)"] == "6.5" and st.values["scans dropped"] == "2"
    assert st.values["particles"] == "4000" and st.values["health"] == "0.90"
    msg = diagnostic_array_msg(st, 12.5, "particle_filter: localization")
    assert msg.status[0].level == b"\x00" and msg.header.stamp.sec == 12
    assert any(kv.key == "sensor updates/s" for kv in msg.status[0].values)
    plog = ProblemLog(period=5.0)
    problems = Watchdog(0.0).problems(1.0)
    assert len(plog.due(problems, 1.0)[0]) == 1  # first time: logged
    assert plog.due(problems, 2.0)[0] == []  # throttled
    assert len(plog.due(problems, 6.5)[0]) == 1
    assert plog.due([], 7.0)[1] == ["no-input"]  # cleared


def test_pose_store_round_trip_and_bad_files(tmp_path):
    path = tmp_path / "p" / "pose.yaml"
    cov = np.diag([0.01, 0.02, 0.003])
    assert pose_store.save_pose(path, [1.0, -2.0, 0.5], cov, "map", 12.25)
    stored, why = pose_store.load_pose(path)
    assert why == "" and np.allclose(stored.pose, [1.0, -2.0, 0.5]) and np.allclose(stored.covariance, cov)
    assert not pose_store.save_pose(tmp_path / "nan.yaml", [math.nan, 0, 0], cov, "map", 0.0)
    (tmp_path / "bad.yaml").write_text("pose: [1, 2]\n")
    assert pose_store.load_pose(tmp_path / "bad.yaml")[0] is None
    assert pose_store.load_pose(tmp_path / "missing.yaml")[0] is None


# ------------------------------------------------------------------ live node


def _collect(node, msg_type, topic, qos=100):
    store, lock = [], threading.Lock()

    def keep(msg):
        with lock:
            store.append(msg)
    node.create_subscription(msg_type, topic, keep, qos)
    return store


def test_no_odometry_gives_a_diagnostics_warning_naming_the_topics(runner, drive, capfd):
    r = runner(odom_timeout=0.5)
    diags = _collect(r.probe, DiagnosticArray, "/diagnostics")
    other_odom = r.probe.create_publisher(Odometry, "/vesc/odom", 10)  # the topic the car really has
    r.send_map(h.map_msg("stata_basement"))
    r.send_initialpose(h.initialpose_msg(drive.initial_guess))
    scans = [e[2] for e in drive.events if e[1] == "scan"]
    t0 = time.monotonic()
    stop = threading.Event()

    def stream():
        for msg in scans:
            if stop.is_set():
                return
            r.probe.scan_pub.publish(msg)
            time.sleep(0.025)
    streamer = threading.Thread(target=stream, daemon=True)
    streamer.start()

    def warned():
        return [s for d in list(diags) for s in d.status
                if s.level == b"\x01" and "scans arrive but no odometry on /odom" in s.message]
    try:
        assert h.wait_until(lambda: warned(), 2.0), [s.message for d in diags for s in d.status]
        assert time.monotonic() - t0 <= 2.1
    finally:
        stop.set()
        streamer.join()
    status = warned()[0]
    assert "/vesc/odom" in status.message  # the odometry topic that does exist is named
    values = {kv.key: kv.value for kv in status.values}
    assert int(values["scans received"]) > 0 and values["seconds since last odometry"] == "never"
    assert other_odom is not None
    assert "WARN: scans arrive but no odometry on /odom" in capfd.readouterr().err  # also logged


def test_initial_pose_from_parameters_without_initialpose(runner, drive):
    x, y, yaw = drive.initial_guess
    r = runner(**{"set_initial_pose": True, "initial_pose.x": float(x), "initial_pose.y": float(y),
                  "initial_pose.yaw": float(yaw)})
    covs = _collect(r.probe, PoseWithCovarianceStamped, "/pf/pose")
    r.send_map(h.map_msg("stata_basement"))
    assert r.node.counts["initialpose"] == 0
    r.play(drive.until(0.5))
    r.settle(0.3)
    poses = r.probe.snapshot()[0]
    assert len(poses) > 10
    assert np.hypot(*(pose_from_msg(poses[-1].pose.pose)[:2] - drive.truth(h.T0_NS + 500_000_000)[:2])) < 0.5
    assert covs and covs[-1].header.frame_id == "map"  # the nav2-style pose output too
    assert covs[-1].pose.covariance[0] > 0


def test_laser_pose_from_tf_static(runner, drive, capfd):
    r = runner()
    qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    pub = r.probe.create_publisher(TFMessage, "/tf_static", qos)
    t = TransformStamped()
    t.header.frame_id, t.child_frame_id = "base_link", "laser"
    t.transform.translation.x, t.transform.translation.y = 0.31, 0.02
    q = yaw_to_quaternion(0.05)
    t.transform.rotation.z, t.transform.rotation.w = float(q[2]), float(q[3])
    pub.publish(TFMessage(transforms=[t]))
    assert h.wait_until(lambda: pub.get_subscription_count() > 0, 5.0)
    r.send_map(h.map_msg("stata_basement"))
    r.send_initialpose(h.initialpose_msg(drive.initial_guess))
    r.settle(0.3)
    r.play(drive.until(0.2))
    assert np.allclose(r.node.localizer.laser_offset, [0.31, 0.02, 0.05], atol=1e-6)
    assert r.node.diagnostic_status().values["laser pose"].startswith("TF")
    pub.publish(TFMessage(transforms=[t]))  # the same mount again, and more scans: no second line
    r.play(drive.until(0.4)[len(drive.until(0.2)):])
    assert capfd.readouterr().err.count("laser pose from TF base_link -> laser") == 1


def test_scans_that_disagree_with_the_map_are_a_diagnostics_warning(runner, drive):
    """Localizing on the drive, then scans of a 0.6 m ring (nothing like the corridor): the localizer
    holds its pose on odometry and /diagnostics says the scans disagree with the map."""
    import copy
    r = runner(health_lost_updates=3, ray_caster="lookup_table")  # the map search of a lost filter: fast enough
    r.send_map(h.map_msg("stata_basement"))
    assert h.wait_until(lambda: r.node.localizer.has_map, 60.0)
    r.send_initialpose(h.initialpose_msg(drive.initial_guess))
    r.settle(0.3)
    events = drive.until(2.0)
    half = len(events) // 2
    r.play(events[:half])
    assert r.node.localizer.status == TRACKING
    assert "disagree" not in {p.key for p in r.node.diagnostic_status().problems}
    for _, kind, msg in events[half:]:
        if kind == "scan":
            msg = copy.deepcopy(msg)
            msg.ranges = [0.6] * len(msg.ranges)
        (r.send_odom if kind == "odom" else r.send_scan)(msg)
    assert h.wait_until(lambda: r.node.localizer.status != TRACKING, 5.0)
    st = r.node.diagnostic_status()
    assert st.level >= WARN and "disagree" in {p.key for p in st.problems}, st.message
    assert "scans disagree with the map" in st.message


def play_past_tf_timeout(r, drive):
    """Map, initial pose, the first 5 events of the drive, a pause longer than a 0.2 s tf_timeout,
    then the rest of its first 0.5 s."""
    r.send_map(h.map_msg("stata_basement"))
    r.send_initialpose(h.initialpose_msg(drive.initial_guess))
    events = drive.until(0.5)
    r.play(events[:5])
    time.sleep(0.3)
    r.play(events[5:])


def test_laser_pose_falls_back_to_parameters_without_tf(runner, drive, capfd):
    r = runner(tf_timeout=0.2, laser_offset_x=0.2, range_scale_estimation=False)  # the scale as configured
    play_past_tf_timeout(r, drive)
    assert capfd.readouterr().err.count("laser pose from the parameters") == 1  # once, not once per scan
    assert np.allclose(r.node.localizer.laser_offset, [0.2, 0.0, 0.0])
    assert r.node.diagnostic_status().values["laser pose"] == "laser_offset_* parameters"
    assert r.node.diagnostic_status().values["range scale"] == "1.0000 (lidar_scale_to_map_scale)"


def test_diagnostics_show_the_range_scale_learnt_online(runner, drive):
    r = runner(range_scale_estimation=True, lidar_scale_to_map_scale=0.99)
    play_past_tf_timeout(r, drive)
    value = r.node.diagnostic_status().values["range scale"]
    assert value.endswith("(learnt online)") and abs(float(value.split()[0]) - 0.99) < 0.0495  # within the bound
    assert float(value.split()[0]) == round(r.node.localizer.range_scale, 4)


def test_diagnostics_show_the_beams_the_last_update_used(runner, drive):
    r = runner(do_beamskip=True, beam_skip_distance=0.15, beam_skip_threshold=0.3)
    assert r.node.diagnostic_status().values["beams used"] == "no sensor update yet"
    play_past_tf_timeout(r, drive)
    assert h.wait_until(lambda: r.node.localizer.beams_used is not None, 5.0)
    r.settle(0.5)  # every scan used: the last update's figure stays
    value = r.node.diagnostic_status().values["beams used"]
    used, offered = r.node.localizer.beams_used
    assert value == f"{used} of {offered} (beam skipping)"
    assert 0 < used <= offered == r.node.params.num_beams_per_particle


def test_broken_tf_tree_is_a_diagnostics_warning(runner, drive):
    r = runner(tf_timeout=0.2)
    qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    pub = r.probe.create_publisher(TFMessage, "/tf_static", qos)
    t = TransformStamped()
    t.header.frame_id, t.child_frame_id = "base_link", "imu"  # TF is there, but not the laser
    t.transform.rotation.w = 1.0
    pub.publish(TFMessage(transforms=[t]))
    assert h.wait_until(lambda: pub.get_subscription_count() > 0, 5.0)
    play_past_tf_timeout(r, drive)
    time.sleep(0.3)
    st = r.node.diagnostic_status()
    assert any(p.key == "tf" for p in st.problems), st.message
    assert "base_link -> laser" in st.message and "imu" in st.message


def test_request_nomotion_update(runner, drive):
    r = runner(update_min_distance=100.0, update_min_angle=100.0)
    r.send_map(h.map_msg("stata_basement"))
    r.send_initialpose(h.initialpose_msg(drive.initial_guess))
    scans = [e for e in drive.events if e[1] == "scan"]
    client = r.probe.create_client(Empty, "/request_nomotion_update")
    assert client.wait_for_service(timeout_sec=5.0)

    def scan_pose_count(t_ns):  # sensor-corrected estimates on /pf/pose, stamped with the scan's time
        return sum(1 for m in r.probe.corrections_snapshot() if h.key(m.header.stamp) == h.ns_key(t_ns))
    r.send_scan(scans[0][2])  # the first scan after an initialisation always updates
    r.send_scan(scans[1][2])  # no motion: no update
    r.settle(0.3)
    assert scan_pose_count(scans[0][0]) == 1 and scan_pose_count(scans[1][0]) == 0
    future = client.call_async(Empty.Request())
    assert h.wait_until(future.done, 5.0)
    r.send_scan(scans[2][2])
    r.send_scan(scans[3][2])
    r.settle(0.3)
    assert scan_pose_count(scans[2][0]) == 1 and scan_pose_count(scans[3][0]) == 0


def test_pose_persisted_and_restored(runner, drive, tmp_path):
    path = tmp_path / "last_pose.yaml"
    params = dict(persist_pose=True, persist_pose_file=str(path), persist_pose_period=0.2)
    r = runner(**params)
    r.send_map(h.map_msg("stata_basement"))
    r.send_initialpose(h.initialpose_msg(drive.initial_guess))
    r.play(drive.until(0.5))
    assert h.wait_until(path.is_file, 3.0)
    r.close()
    stored, _ = pose_store.load_pose(path)
    final = r.node.localizer.estimate.pose
    assert np.allclose(stored.pose, final, atol=1e-3)  # the last write is at shutdown

    r2 = runner(**params)
    assert not r2.node.localizer.ready  # the pose is set from the file; localizing needs the map too
    r2.send_map(h.map_msg("stata_basement"))
    assert r2.node.localizer.ready and r2.node.counts["initialpose"] == 0
    assert np.hypot(*(r2.node.localizer.estimate.pose[:2] - stored.pose[:2])) < 0.3


def test_lifecycle_transitions(context, drive):
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState, GetState

    with h.lifecycle_running(context, "pf_lifecycle_probe") as (node, probe):
        change = probe.create_client(ChangeState, "/particle_filter/change_state")
        get = probe.create_client(GetState, "/particle_filter/get_state")

        def transition(tid):
            req = ChangeState.Request()
            req.transition.id = tid
            fut = change.call_async(req)
            assert h.wait_until(fut.done, 20.0)
            return fut.result().success

        def state():
            fut = get.call_async(GetState.Request())
            assert h.wait_until(fut.done, 5.0)
            return fut.result().current_state.label

        assert change.wait_for_service(timeout_sec=10.0)
        assert state() == "unconfigured"
        assert probe.scan_pub.get_subscription_count() == 0
        assert transition(Transition.TRANSITION_CONFIGURE) and state() == "inactive"
        assert probe.scan_pub.get_subscription_count() == 0  # configured, not yet listening
        assert transition(Transition.TRANSITION_ACTIVATE) and state() == "active"
        probe.wait_connected()
        probe.map_pub.publish(h.map_msg("stata_basement"))
        assert h.wait_until(lambda: node.counts["map"] == 1, 20.0)
        probe.initialpose_pub.publish(h.initialpose_msg(drive.initial_guess))
        assert h.wait_until(lambda: node.counts["initialpose"] == 1, 5.0)
        for _, kind, msg in drive.until(0.3):
            (probe.odom_pub if kind == "odom" else probe.scan_pub).publish(msg)
            time.sleep(0.01)
        assert h.wait_until(lambda: len(probe.snapshot()[0]) > 5, 5.0)
        assert transition(Transition.TRANSITION_DEACTIVATE) and state() == "inactive"
        assert h.wait_until(lambda: probe.scan_pub.get_subscription_count() == 0, 5.0)
        assert transition(Transition.TRANSITION_CLEANUP) and state() == "unconfigured"
        assert node.localizer is None or node.map_install is None
        assert transition(Transition.TRANSITION_CONFIGURE) and state() == "inactive"  # again, after cleanup


def test_cold_start_builds_the_table_off_thread_and_reports_truthfully(runner, drive, tmp_path, monkeypatch,
                                                                     capfd):
    from localization.core.raycast import lookup_table
    monkeypatch.setenv("LOCALIZATION_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(lookup_table, "LIVE_TABLES", {})
    r = runner(ray_caster="lookup_table", scan_theta_discretization=16)
    original = r.node.localizer.prepare_ray_caster
    building = threading.Event()

    def slow_prepare(m):  # a slow machine: the build takes a while, inputs keep coming meanwhile
        building.set()
        caster = original(m)
        time.sleep(1.0)
        return caster
    r.node.localizer.prepare_ray_caster = slow_prepare
    r.send_initialpose(h.initialpose_msg(drive.initial_guess))
    r.probe.map_pub.publish(h.map_msg("stata_basement"))
    assert building.wait(10.0)
    events = drive.events
    k = 0
    while r.node.counts["map"] == 0 and k < len(events):  # stream while the table is prepared
        _, kind, msg = events[k]
        (r.send_odom if kind == "odom" else r.send_scan)(msg)
        k += 1
        time.sleep(0.02)
    assert h.wait_until(lambda: r.node.counts["map"] == 1, 60.0)
    w = r.node.watchdog
    assert w.scans_waiting_for_table > 0 and w.odom_waiting_for_table > 0
    # the scans that came during the build could not be used: /diagnostics says so (WARN)
    status = r.node.diagnostic_status()
    assert status.level >= WARN and "scans-dropped" in {p.key for p in status.problems}
    # every scan the build kept from use is counted as such; a scan in flight as the table came may still land
    # before the initial pose is applied and is counted (and said) as waiting for it
    assert "range table" in status.message and 0 <= w.scans_dropped - w.scans_waiting_for_table <= 2
    assert h.wait_until(lambda: len(r.probe.snapshot()[0]) > 0, 5.0)  # the first pose once the table is ready
    # the odometry of the build was kept: the first pose is where the car drove meanwhile, not where it started
    first = r.probe.snapshot()[0][0]
    t_first = first.header.stamp.sec * 10**9 + first.header.stamp.nanosec
    travelled = drive.speed * (t_first - h.T0_NS) * 1e-9
    assert travelled > 0.5
    assert np.hypot(*(odom_xy(first) - drive.truth(t_first)[:2])) < 0.5 + 0.05 * travelled
    r.play(events[k:k + 20])
    r.settle(0.2)
    log = capfd.readouterr().err
    assert "range table: building it" in log and "expected ~" in log and "odometry is kept meanwhile" in log
    assert "range table built in" in log
    assert "no map received yet" not in log and "stamp jumped" not in log, log
    assert "waiting for the sensor model to prepare the map" in log  # the scans' throttled line
    assert list((tmp_path / "cache").iterdir())  # cached for the next start


def odom_xy(msg) -> np.ndarray:
    return np.array([msg.pose.pose.position.x, msg.pose.pose.position.y])


# ------------------------------------------------------------------ command line
def _script(name):
    script = Path(sys.executable).parent / name
    return [str(script)] if script.exists() else [sys.executable, "-m", "localization.particle_filter"]


def test_help_prints_usage_and_exits():
    out = subprocess.run(_script("particle_filter") + ["--help"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "usage:" in out.stdout and "odom_timeout" in out.stdout
    assert "particle filter ready" not in out.stdout + out.stderr
    script = Path(sys.executable).parent / "particle_filter_lifecycle"
    cmd = [str(script)] if script.exists() else [sys.executable, "-m", "localization.ros.lifecycle_node"]
    out = subprocess.run(cmd + ["-h"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "usage:" in out.stdout


def test_missing_parameter_file_is_one_line():
    out = subprocess.run(_script("particle_filter") + ["--ros-args", "--params-file", "/nonexistent/p.yaml"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 1
    assert "parameter file not found" in out.stderr and "Traceback" not in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1


def test_parameter_file_by_name_and_clean_ctrl_c():
    env = dict(os.environ)
    proc = subprocess.Popen(_script("particle_filter") + ["--ros-args", "--params-file", "real_params", "-p",
                                                           "ray_caster:=distance_transform"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    deadline = time.monotonic() + 60
    lines = []
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        lines.append(line)
        if "particle filter ready" in line:
            break
    proc.send_signal(signal.SIGINT)
    out = "".join(lines) + proc.communicate(timeout=20)[0]
    assert proc.returncode == 0, out
    assert "particle filter ready" in out and "/vesc/odom" in out  # real_params was found by name
    assert "Failed to publish log message to rosout" not in out
    assert "Traceback" not in out and "scans: 0 received" in out


def test_play_publishes_a_latched_map_and_an_initial_pose(context):
    """`localization-play --map NAME --initial-pose X,Y,YAW`: what a pip-only user has instead of ros2 CLI."""
    from nav_msgs.msg import OccupancyGrid
    node = rclpy.create_node("pf_play_listener", context=context)
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(node)
    qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    maps = _collect(node, OccupancyGrid, "/map", qos)
    poses = _collect(node, PoseWithCovarianceStamped, "/initialpose", 10)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    proc = subprocess.Popen([sys.executable, "-m", "localization.tools.play", "--map", "stata_basement",
                             "--initial-pose=-6.0,20.0,-2.24"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, env=dict(os.environ), cwd=REPO)
    try:
        assert h.wait_until(lambda: maps and poses, 30.0), "no map or initial pose received"
        assert maps[0].info.width > 0 and maps[0].header.frame_id == "map"
        assert np.allclose(pose_from_msg(poses[0].pose.pose), [-6.0, 20.0, -2.24])
        assert proc.poll() is None  # the map stays available (latched) until Ctrl-C
    finally:
        proc.send_signal(signal.SIGINT)
        out = proc.communicate(timeout=20)[0]
        executor.shutdown(timeout_sec=5.0)
        spinner.join(timeout=5.0)
        node.destroy_node()
    assert proc.returncode == 0, out
    assert "Traceback" not in out


def test_play_refuses_a_map_image():
    out = subprocess.run([sys.executable, "-m", "localization.tools.play", "--map", "basement_fixed.png"],
                         capture_output=True, text=True, timeout=60, cwd=REPO)
    assert out.returncode == 2 and "basement_fixed.yaml" in out.stderr and "Traceback" not in out.stderr


# ------------------------------------------------------------------ launch file, RViz config, docs (static)
def test_car_launch_file_arguments_and_referenced_files():
    """The launch package is not installed here: parse the file and check what it references."""
    import ast
    source = (REPO / "launch" / "localization_car.launch.py").read_text()
    tree = ast.parse(source)
    declared = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and getattr(node.func, "id", "") == "DeclareLaunchArgument":
            name = node.args[0].value
            default = next((k.value for k in node.keywords if k.arg == "default_value"), None)
            declared[name] = ast.unparse(default) if default is not None else None
    assert {"map", "params_file", "rviz", "lifecycle", "use_sim_time", "set_initial_pose"} <= set(declared)
    assert "real_params.yaml" in declared["params_file"]  # the car's parameters by default
    default_map = next(n.value for n in ast.walk(tree) if isinstance(n, ast.Assign)
                       and getattr(n.targets[0], "id", "") == "DEFAULT_MAP").value
    assert (REPO / "maps" / f"{default_map}.yaml").is_file()
    assert (REPO / "config" / "real_params.yaml").is_file() and (REPO / "rviz" / "localization.rviz").is_file()
    packages = {k.value.value for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "Node"
                for k in n.keywords if k.arg == "package" and isinstance(k.value, ast.Constant)}
    assert {"nav2_map_server", "nav2_lifecycle_manager", "rviz2"} <= packages
    package_xml = (REPO / "package.xml").read_text()
    for dep in ("diagnostic_msgs", "lifecycle_msgs"):  # the node's own
        assert f"<exec_depend>{dep}</exec_depend>" in package_xml, dep
    for dep in packages - {"localization"}:  # the launch's bringup pieces: named for whoever installs them
        assert dep in package_xml, dep
    setup = (REPO / "setup.py").read_text()
    assert "particle_filter_lifecycle = localization.ros.lifecycle_node:main" in setup
    assert 'glob("rviz/*.rviz")' in setup and 'glob("launch/*.py")' in setup
    # the map argument: a name of maps/ or a YAML path
    namespace = {}
    func = next(n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "resolve_map")
    exec("import os\n" + ast.get_source_segment(source, func), namespace)
    assert namespace["resolve_map"]("stata_basement", "/share") == "/share/maps/stata_basement.yaml"
    assert namespace["resolve_map"]("/x/my.yaml", "/share") == "/x/my.yaml"


def test_rviz_config_shows_map_scan_particles_pose_and_tf():
    import yaml
    doc = yaml.safe_load((REPO / "rviz" / "localization.rviz").read_text())
    displays = doc["Visualization Manager"]["Displays"]
    topics = {d["Class"].split("/")[-1]: d.get("Topic", {}).get("Value") for d in displays}
    assert topics["Map"] == "/map" and topics["LaserScan"] == "/scan" and topics["PoseArray"] == "/pf/particles"
    assert topics["PoseWithCovariance"] == "/pf/pose" and "TF" in topics
    assert doc["Visualization Manager"]["Global Options"]["Fixed Frame"] == "map"


def test_node_doc_has_no_machine_specific_paths():
    import re
    text = (REPO / "docs" / "node.md").read_text()
    assert not re.search(r"(?<![\w.])/(work|home|root|tmp|Users)/", text), re.findall(r"/(?:work|home|root)/\S+", text)
    for word in ("localization_car.launch.py", "Foxglove", "set_initial_pose", "/diagnostics", "odom_timeout"):
        assert word in text


def test_wrong_type_message_grammar():
    from localization.core.parameters import ParameterError, Parameters
    with pytest.raises(ParameterError) as exc:
        Parameters(num_particles="many", deterministic=3, map_topic=1)
    text = str(exc.value)
    assert "must be an integer" in text and "must be a boolean" in text and "must be a string" in text
    assert "a int" not in text and "a bool" not in text.replace("a boolean", "")


def test_parameter_file_accepts_nested_initial_pose(tmp_path):
    from localization.core.parameters import Parameters
    path = tmp_path / "p.yaml"
    path.write_text("particle_filter:\n  ros__parameters:\n    set_initial_pose: true\n"
                    "    initial_pose: {x: 1.5, y: -2.0, yaw: 0.5}\n")
    p = Parameters.from_yaml(path)
    assert p.set_initial_pose and (p["initial_pose.x"], p["initial_pose.y"], p["initial_pose.yaw"]) == (1.5, -2.0, 0.5)


def test_republished_map_in_another_frame_says_what_happens_to_the_particles(runner, drive, capfd):
    r = runner()
    r.send_map(h.map_msg("stata_basement"))
    r.send_initialpose(h.initialpose_msg(drive.initial_guess))
    other = h.map_msg("stata_basement")
    other = type(other)(header=type(other.header)(frame_id="world"), info=other.info, data=other.data)
    capfd.readouterr()
    r.send_map(other)
    err = capfd.readouterr().err
    assert "'world' differs from map_frame 'map'" in err
    assert "particles are kept" in err and "initial pose" in err
