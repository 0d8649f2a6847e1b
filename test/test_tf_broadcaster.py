"""localization.tf_broadcaster end to end: a real publisher and a plain tf2_msgs/TFMessage subscriber.

Both nodes live in this process, in an rclpy Context of the test's own (conftest.py keeps DDS on
loopback in a per-run domain). In a pip venv the broadcaster uses the tf2_msgs fallback (built by
scripts/build_tf2_msgs.sh); where tf2_ros is importable both backends are tested.
"""
import time

import pytest
import rclpy
from geometry_msgs.msg import TransformStamped
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from localization.ros import tf_broadcaster
from localization.ros.tf_broadcaster import TransformBroadcaster

try:
    from tf2_msgs.msg import TFMessage
except ImportError:  # pragma: no cover - environment problem, reported by the fixture below
    TFMessage = None

try:
    import tf2_ros  # noqa: F401
    HAVE_TF2_ROS = True
except ImportError:
    HAVE_TF2_ROS = False

# Official ROS 2 Jazzy type hash of tf2_msgs/msg/TFMessage.
TFMESSAGE_HASH = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"
TIMEOUT_S = 8.0  # generous bound for a loaded 2-core CI machine; normally < 1 s


# The fallback is always tested; tf2_ros's broadcaster too where it is installed (a full ROS install).
@pytest.fixture(params=["tf2_msgs"] + (["tf2_ros"] if HAVE_TF2_ROS else []))
def backend(request, monkeypatch):
    if TFMessage is None:
        pytest.fail("tf2_msgs is not importable: run scripts/build_tf2_msgs.sh in this venv", pytrace=False)
    if request.param == "tf2_msgs":
        monkeypatch.setattr(tf_broadcaster, "tf2_ros", None)  # force the fallback
    return request.param


@pytest.fixture
def ros():
    """(context, executor, create_node) on a Context of this test's own, shut down afterwards."""
    context = Context()
    rclpy.init(context=context)
    executor = SingleThreadedExecutor(context=context)
    nodes = []

    def create_node(name):
        node = rclpy.create_node(name, context=context)
        executor.add_node(node)
        nodes.append(node)
        return node

    try:
        yield context, executor, create_node
    finally:
        for node in nodes:
            executor.remove_node(node)
            node.destroy_node()
        executor.shutdown()
        rclpy.shutdown(context=context)


def spin_until(executor, condition, timeout=TIMEOUT_S):
    deadline = time.monotonic() + timeout
    while not condition() and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    return condition()


def spin_for(executor, duration):
    deadline = time.monotonic() + duration
    while time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)


def make_transform(parent, child, sec, nanosec, xyz, xyzw):
    t = TransformStamped()
    t.header.frame_id = parent
    t.header.stamp.sec, t.header.stamp.nanosec = sec, nanosec
    t.child_frame_id = child
    t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = xyz
    r = t.transform.rotation
    r.x, r.y, r.z, r.w = xyzw
    return t


def as_tuple(t):
    tr, r = t.transform.translation, t.transform.rotation
    return (t.header.frame_id, t.child_frame_id, t.header.stamp.sec, t.header.stamp.nanosec,
            (tr.x, tr.y, tr.z), (r.x, r.y, r.z, r.w))


def test_dynamic_transform_reaches_tf_subscriber(backend, ros):
    _, executor, create_node = ros
    pub_node = create_node("tf_broadcaster_test_pub")
    sub_node = create_node("tf_broadcaster_test_sub")
    received = []
    sub_node.create_subscription(TFMessage, "/tf", received.append, QoSProfile(depth=100))

    broadcaster = TransformBroadcaster(pub_node)
    assert broadcaster.backend == backend
    # Publish only once the DDS writer has matched the reader, so the one message is not lost.
    assert spin_until(executor, lambda: broadcaster.publisher.get_subscription_count() >= 1)

    sent = make_transform("map", "base_link_pf", 1_700_000_123, 456_789_000,
                          (1.25, -3.5, 0.0), (0.0, 0.0, 0.38268343236508984, 0.9238795325112867))
    broadcaster.send([sent])
    assert spin_until(executor, lambda: received), "no TFMessage received on /tf"
    spin_for(executor, 0.3)  # anything extra would arrive now

    assert len(received) == 1
    assert [as_tuple(t) for t in received[0].transforms] == [
        ("map", "base_link_pf", 1_700_000_123, 456_789_000,
         (1.25, -3.5, 0.0), (0.0, 0.0, 0.38268343236508984, 0.9238795325112867)),
    ]

    # The publisher is a real tf2_msgs/msg/TFMessage one with the official Jazzy type hash and the
    # QoS of tf2_ros's TransformBroadcaster.
    (info,) = sub_node.get_publishers_info_by_topic("/tf")
    assert info.topic_type == "tf2_msgs/msg/TFMessage"
    assert str(info.topic_type_hash) == TFMESSAGE_HASH
    assert info.qos_profile.reliability == ReliabilityPolicy.RELIABLE
    assert info.qos_profile.durability == DurabilityPolicy.VOLATILE


def test_static_transforms_reach_late_joining_subscriber(backend, ros):
    _, executor, create_node = ros
    pub_node = create_node("tf_static_broadcaster_test_pub")
    broadcaster = TransformBroadcaster(pub_node, static=True)
    assert broadcaster.backend == backend

    laser = make_transform("base_link_pf", "laser", 0, 0, (0.27, 0.0, 0.11), (0.0, 0.0, 0.0, 1.0))
    odom = make_transform("map", "odom", 12, 34, (-1.0, 2.0, 0.0), (0.0, 0.0, 1.0, 0.0))
    # Two sends, nobody listening yet: the latched message must still carry both transforms.
    broadcaster.send([laser])
    broadcaster.send([odom])
    spin_for(executor, 0.2)

    sub_node = create_node("tf_static_broadcaster_test_sub")
    received = []
    static_qos = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST,
                            reliability=ReliabilityPolicy.RELIABLE,
                            durability=DurabilityPolicy.TRANSIENT_LOCAL)
    sub_node.create_subscription(TFMessage, "/tf_static", received.append, static_qos)
    assert spin_until(executor, lambda: received), "late subscriber got nothing on /tf_static"
    spin_for(executor, 0.3)

    assert len(received) == 1
    assert sorted(as_tuple(t) for t in received[0].transforms) == sorted([
        ("base_link_pf", "laser", 0, 0, (0.27, 0.0, 0.11), (0.0, 0.0, 0.0, 1.0)),
        ("map", "odom", 12, 34, (-1.0, 2.0, 0.0), (0.0, 0.0, 1.0, 0.0)),
    ])
    (info,) = sub_node.get_publishers_info_by_topic("/tf_static")
    assert str(info.topic_type_hash) == TFMESSAGE_HASH
    assert info.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL


def test_missing_tf2_ros_and_tf2_msgs_names_the_build_script(monkeypatch):
    monkeypatch.setattr(tf_broadcaster, "tf2_ros", None)
    monkeypatch.setitem(__import__("sys").modules, "tf2_msgs.msg", None)  # makes the import fail
    with pytest.raises(ImportError, match="scripts/build_tf2_msgs.sh"):
        TransformBroadcaster(node=None)
