"""Tests for localization-play: replay a written bag into a subscriber in this process."""
import importlib.util
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from localization.bags import BagWriter, make_laser_scan, make_odometry, make_tf_message, make_transform_stamped
from localization.tools.play import main as play_main

REPO = Path(__file__).resolve().parents[1]
T0 = 1_650_000_000_000_000_000
N_SCANS = 20  # 10 Hz over 1.9 s
N_ODOM = 40  # 20 Hz over 1.95 s
RATE = 4.0
N_BEAMS = 100

rclpy = pytest.importorskip("rclpy")


def _env() -> dict:
    env = dict(os.environ)  # conftest.py set ROS_DOMAIN_ID and ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env["PYTHONUNBUFFERED"] = "1"
    return env


def _play(*args, timeout=30.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "localization.tools.play", *map(str, args)], cwd=REPO, env=_env(),
                          capture_output=True, text=True, timeout=timeout)


@pytest.fixture
def small_bag(tmp_path):
    path = tmp_path / "play_bag"
    with BagWriter(path) as w:
        ts = w.typestore
        w.write("/tf_static", T0, make_tf_message(ts, [make_transform_stamped(ts, T0, "base_link", "laser", 0.275)]))
        for k in range(N_SCANS):
            t = T0 + k * 100_000_000
            ranges = np.full(N_BEAMS, 1.0 + k, dtype=np.float32)
            w.write("/scan", t, make_laser_scan(ts, t, "laser", ranges, angle_min=-1.0, angle_max=1.0,
                                                angle_increment=2.0 / (N_BEAMS - 1), range_min=0.02, range_max=30.0))
        for k in range(N_ODOM):
            t = T0 + 5_000_000 + k * 50_000_000
            w.write("/odom", t, make_odometry(ts, t, "odom", "base_link", x=0.1 * k, y=0.0, yaw=0.0, vx=2.0))
    return path


def test_play_republishes_bag(small_bag):
    from nav_msgs.msg import Odometry
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import LaserScan

    context = Context()
    rclpy.init(context=context)
    received = {"/scan": [], "/odom": []}
    arrival = {"/scan": [], "/odom": []}
    executor = spinner = node = None
    try:
        node = rclpy.create_node("test_play_listener", context=context)
        reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        best_effort = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)

        def keep(topic):
            def cb(msg):
                received[topic].append(msg)
                arrival[topic].append(time.monotonic())
            return cb

        node.create_subscription(LaserScan, "/scan", keep("/scan"), reliable)
        node.create_subscription(Odometry, "/odom", keep("/odom"), best_effort)  # reliable pub matches it too
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        spinner = threading.Thread(target=executor.spin, daemon=True)
        spinner.start()

        proc = _play(small_bag, "--rate", RATE, "--start-delay", 4.0, "--end-delay", 0.5)  # discovery under load
        assert proc.returncode == 0, proc.stderr
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline and (len(received["/scan"]) < N_SCANS or len(received["/odom"]) < N_ODOM):
            time.sleep(0.05)
    finally:
        if executor is not None:
            executor.shutdown(timeout_sec=2.0)
        if spinner is not None:
            spinner.join(timeout=2.0)
        if node is not None:
            node.destroy_node()
        rclpy.shutdown(context=context)

    assert len(received["/scan"]) == N_SCANS, proc.stderr
    assert len(received["/odom"]) == N_ODOM, proc.stderr
    scans = received["/scan"]
    assert [s.ranges[0] for s in scans] == [1.0 + k for k in range(N_SCANS)]  # order and values kept
    assert len(scans[3].ranges) == N_BEAMS and scans[3].header.frame_id == "laser"
    assert scans[3].header.stamp.sec == (T0 + 3 * 100_000_000) // 10**9
    assert scans[3].header.stamp.nanosec == (T0 + 3 * 100_000_000) % 10**9
    assert received["/odom"][-1].pose.pose.position.x == pytest.approx(0.1 * (N_ODOM - 1))
    assert received["/odom"][-1].child_frame_id == "base_link"
    # Played at bag time / RATE: the bag's 1.9 s of scans arrive over ~0.475 s.
    span = arrival["/scan"][-1] - arrival["/scan"][0]
    assert 0.3 < span < 1.5, span

    summary = proc.stdout.strip().splitlines()[-1]
    assert f"{N_SCANS} /scan" in summary and f"{N_ODOM} /odom" in summary
    if importlib.util.find_spec("tf2_msgs") is None:
        assert "skipping /tf_static" in proc.stderr
    else:
        assert "1 /tf_static" in summary


def test_play_missing_bag_exits_nonzero(tmp_path):
    proc = _play(tmp_path / "no_such.bag", timeout=20.0)
    assert proc.returncode != 0
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "bag not found" in lines[0] and "no_such.bag" in lines[0], proc.stderr


def test_play_unknown_topic_is_an_error(small_bag, capsys):
    assert play_main([str(small_bag), "--topics", "/scan", "/nope"]) == 2
    err = capsys.readouterr().err
    assert "/nope" in err and "/scan" in err
