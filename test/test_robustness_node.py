"""The node and localization-replay survive broken input: real rclpy messages with hypothesis-made
contents go through the node's callbacks; a corrupted bag goes through localization-replay."""
import array
import json
import math

import node_harness as h
import numpy as np
import pytest
from helpers import corridor_map
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from rclpy.parameter import Parameter

from localization.eval.corrupt import corrupt_bag
from localization.eval.datasets import trial_config
from localization.ros.messages import occupancy_grid_msg
from localization.ros.node import ParticleFilterNode
from localization.sim import record
from localization.tools import replay as R

FLOATS = st.floats(allow_nan=True, allow_infinity=True, width=64)
SMALL = st.one_of(st.floats(-5.0, 5.0), FLOATS)
STAMP_NS = st.integers(0, 2**62)


class Recorder:
    """Stands in for a publisher / TF broadcaster: keeps what the node sends."""

    def __init__(self):
        self.sent = []

    def publish(self, msg):
        self.sent.append(msg)

    send = send_serialized = publish


def _finite_msg(msg) -> bool:
    name = type(msg).__name__
    if name == "Odometry":
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        vals = [p.x, p.y, p.z, q.x, q.y, q.z, q.w, *msg.pose.covariance]
    elif name == "PoseArray":
        vals = [v for pose in msg.poses for v in (pose.position.x, pose.position.y, pose.orientation.z,
                                                    pose.orientation.w)]
    elif name == "Float32":
        vals = [msg.data]
        if not 0.0 <= msg.data <= 1.0:
            return False
    elif name == "TFMessage":
        vals = [v for tf in msg.transforms for v in (tf.transform.translation.x, tf.transform.translation.y,
                                                     tf.transform.rotation.z, tf.transform.rotation.w)]
    else:
        raise AssertionError(f"unexpected output {name}")
    return bool(np.all(np.isfinite(np.asarray(vals, dtype=float))))


@pytest.fixture(scope="module")
def node():
    ctx = h.init_context()
    n = ParticleFilterNode(context=ctx, parameter_overrides=[
        Parameter("num_particles", value=300), Parameter("global_num_particles", value=1500),
        Parameter("ray_caster", value="distance_transform"), Parameter("random_seed", value=3)])
    out = n.outputs  # the node's publishers
    out.pose_pub, out.particles_pub, out.health_pub, out.tf = Recorder(), Recorder(), Recorder(), Recorder()
    good_map = occupancy_grid_msg(corridor_map())
    n.on_map(good_map)
    n.on_initialpose(h.initialpose_msg([5.0, 1.5, 0.0]))
    n.good_map = good_map
    yield n
    n.destroy_node()
    import rclpy
    rclpy.shutdown(context=ctx)


def _outputs(n):
    """Everything the node sent, as messages (the pose, the cloud and TF go out serialized)."""
    from geometry_msgs.msg import PoseArray
    from nav_msgs.msg import Odometry
    from rclpy.serialization import deserialize_message
    from tf2_msgs.msg import TFMessage

    def read(sent, kind):
        return [deserialize_message(m, kind) if isinstance(m, bytes) else m for m in sent]
    out = n.outputs
    return [*read(out.pose_pub.sent, Odometry), *read(out.particles_pub.sent, PoseArray), *out.health_pub.sent,
            *read(out.tf.sent, TFMessage)]


def _clear(n):
    for r in (n.outputs.pose_pub, n.outputs.particles_pub, n.outputs.health_pub, n.outputs.tf):
        r.sent.clear()


# ------------------------------------------------------------------ message strategies
@st.composite
def scans(draw):
    n = draw(st.sampled_from([0, 1, 2, 50, 1081]))
    base = draw(st.sampled_from([np.nan, np.inf, -np.inf, -1.0, 0.0, 1e30, 1.2, 3.0]))
    ranges = np.full(n, base)
    if n and draw(st.booleans()):
        ranges = np.asarray(draw(st.lists(FLOATS, min_size=n, max_size=n)) if n <= 50 else
                            np.random.default_rng(draw(st.integers(0, 99))).uniform(-1, 40, n))
    t_ns = draw(STAMP_NS)
    msg = h.scan_msg(t_ns, np.zeros(0))
    msg.angle_min, msg.angle_max, msg.angle_increment = draw(SMALL), draw(SMALL), draw(SMALL)
    msg.range_min, msg.range_max = draw(SMALL), draw(st.one_of(st.just(30.0), FLOATS))
    with np.errstate(over="ignore", invalid="ignore"):
        msg.ranges = array.array("f", np.asarray(ranges, dtype=np.float32).tobytes())
    return msg


@st.composite
def odoms(draw):
    msg = h.odom_msg(draw(STAMP_NS), [draw(SMALL), draw(SMALL), draw(SMALL)], 0.0)
    msg.twist.twist.linear.x, msg.twist.twist.linear.y = draw(SMALL), draw(SMALL)
    msg.twist.twist.angular.z = draw(SMALL)
    return msg


@st.composite
def initialposes(draw):
    msg = h.initialpose_msg([draw(st.one_of(st.floats(-2, 12), FLOATS)), draw(st.one_of(st.floats(-1, 4), FLOATS)),
                             draw(SMALL)], draw(STAMP_NS), draw(st.sampled_from(["map", "", "odom", "base_link"])))
    if draw(st.booleans()):
        msg.pose.covariance = [draw(FLOATS) if i in (0, 7, 35, 1) else 0.0 for i in range(36)]
    if draw(st.booleans()):
        msg.pose.pose.orientation.w = draw(FLOATS)  # not a unit quaternion, maybe NaN
    return msg


@st.composite
def maps(draw):
    kind = draw(st.sampled_from(["unknown", "occupied", "zero_res", "bad_len", "other_size", "random", "good"]))
    w, hgt = draw(st.integers(0, 40)), draw(st.integers(0, 40))
    msg = occupancy_grid_msg(corridor_map())
    if kind == "good":
        return msg
    if kind == "other_size":
        return occupancy_grid_msg(corridor_map(width_cells=120, height_cells=40, wall_rows=(5, 30)))
    msg.info.width, msg.info.height = w, hgt
    fill = {"unknown": -1, "occupied": 100}.get(kind, 0)
    data = np.full(w * hgt, fill, dtype=np.int8)
    if kind == "random":
        data = np.random.default_rng(draw(st.integers(0, 99))).choice(np.array([-1, 0, 100, 50, -7], dtype=np.int8),
                                                                      w * hgt)
    if kind == "bad_len":
        data = data[: max(w * hgt - 3, 0)]
    msg.data = array.array("b", data.tobytes())
    msg.info.resolution = 0.0 if kind == "zero_res" else draw(st.sampled_from([0.05, -0.05, math.nan, math.inf, 0.05]))
    return msg


def _wire(kind, messages):
    """(kind, a message as the node's subscription delivers it (CDR bytes) or as a message object)."""
    from rclpy.serialization import serialize_message
    return st.tuples(messages, st.booleans()).map(lambda m: (kind, serialize_message(m[0]) if m[1] else m[0]))


MESSAGES = st.one_of(_wire("scan", scans()), _wire("odom", odoms()),
                     initialposes().map(lambda m: ("initialpose", m)), maps().map(lambda m: ("map", m)))


@settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))
@given(stream=st.lists(MESSAGES, min_size=1, max_size=12))
def test_node_callbacks_survive_broken_messages_and_never_publish_nan(node, stream):
    n = node
    # a known-good state first (a good map and pose, as a user would send), so each example stands alone
    n.on_map(n.good_map)
    assert h.wait_until(lambda: n.map_install.idle, 30.0)  # maps are installed on their own thread
    n.on_initialpose(h.initialpose_msg([5.0, 1.5, 0.0]))
    _clear(n)
    handlers = {"scan": n.process_scan, "odom": n.on_odometry, "initialpose": n.on_initialpose, "map": n.on_map}
    for kind, msg in stream:
        handlers[kind](msg)  # must not raise
    assert h.wait_until(lambda: n.map_install.idle, 30.0)
    bad = [m for m in _outputs(n) if not _finite_msg(m)]
    assert not bad
    assert np.all(np.isfinite(n.localizer.particles()))
    if n.localizer.estimate is not None:
        assert np.all(np.isfinite(n.localizer.estimate.pose))


def test_node_keeps_working_after_broken_input_and_publishes_health(node):
    n = node
    n.on_map(n.good_map)
    assert h.wait_until(lambda: n.map_install.idle, 30.0)  # maps are installed on their own thread
    n.on_initialpose(h.initialpose_msg([5.0, 1.5, 0.0]))
    _clear(n)
    from localization.core.raycast.exact import ExactRayCaster
    angles = h.ANGLE_MIN + np.arange(h.NUM_BEAMS) * h.ANGLE_INC
    t0 = h.T0_NS + 10**12
    pose = np.array([5.0, 1.5, 0.0])
    for k in range(40):
        t_ns = t0 + k * 20_000_000
        pose = pose + [0.02, 0.0, 0.0]
        n.on_odometry(h.odom_msg(t_ns, pose, 1.0))
        if k % 7 == 3:  # broken messages in between
            n.on_odometry(h.odom_msg(t_ns, pose, float("nan")))
            bad = h.scan_msg(t_ns, np.full(h.NUM_BEAMS, np.nan))
            n.process_scan(bad)
        laser = pose + [0.275, 0.0, 0.0]
        n.process_scan(h.scan_msg(t_ns, ExactRayCaster(n.localizer.map, 10.0).cast(laser[None], angles)[0]))
    assert len(n.outputs.pose_pub.sent) > 30 and len(n.outputs.health_pub.sent) > 10
    assert all(_finite_msg(m) for m in _outputs(n))
    assert n.outputs.health_pub.sent[-1].data > 0.7
    assert np.hypot(*(n.localizer.estimate.pose[:2] - pose[:2])) < 0.2


def test_unreadable_input_bytes_are_logged_and_ignored(node, capfd):
    """Bytes on /scan or the odometry topic that are not the message (cut short, another encoding): one
    warning each, nothing published, and the node goes on with the next good message."""
    from rclpy.serialization import serialize_message
    n = node
    n.on_map(n.good_map)
    assert h.wait_until(lambda: n.map_install.idle, 30.0)
    n.on_initialpose(h.initialpose_msg([5.0, 1.5, 0.0]))
    _clear(n)
    odom = serialize_message(h.odom_msg(h.T0_NS + 2 * 10**12, [5.0, 1.5, 0.0], 0.0))
    scan = serialize_message(h.scan_msg(h.T0_NS + 2 * 10**12, np.full(h.NUM_BEAMS, 3.0)))
    n.on_odometry(odom[:-9])
    n.process_scan(scan[:40])
    n.process_scan(b"\x00\x07\x00\x00" + scan[4:])
    assert not _outputs(n)
    err = capfd.readouterr().err
    assert "odometry message on /odom ignored: truncated" in err
    assert "scan message on /scan ignored: truncated" in err
    for k in range(3):  # a new history after the earlier tests' stamps: it starts at the second message
        n.on_odometry(serialize_message(h.odom_msg(h.T0_NS + 2 * 10**12 + k * 20_000_000, [5.0, 1.5, 0.0], 0.0)))
    assert n.outputs.pose_pub.sent and all(_finite_msg(m) for m in _outputs(n))


# ------------------------------------------------------------------ localization-replay
def test_corrupted_bag_through_replay_gives_nan_free_poses(tmp_path):
    clean = tmp_path / "clean"
    record(trial_config("trial2_noise0.3", duration=5.0), clean)
    bad = tmp_path / "bad"
    counts = corrupt_bag(clean, bad, fraction=0.2, seed=1)
    assert sum(counts.values()) > 50 and len(counts) >= 12
    out = tmp_path / "out"
    assert R.main([str(bad), "--map", "stata_basement", "--out", str(out), "--no-plots", "--quiet",
                   "-p", "ray_caster=lookup_table"]) == 0
    poses = np.loadtxt(out / "poses.csv", delimiter=",", skiprows=1, ndmin=2)
    assert len(poses) > 100 and not np.isnan(poses).any()
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["recoveries"] == 0 and metrics["health"]["median"] > 0.8
    assert metrics["ct_error_m"]["mean"] < 0.15
