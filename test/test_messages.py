"""Core -> ROS message builders (localization.messages): content, frames, stamps, NaN guards."""
from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("nav_msgs.msg")

from builtin_interfaces.msg import Time  # noqa: E402
from geometry_msgs.msg import Pose, PoseArray  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402

from localization.core.geometry import compose  # noqa: E402
from localization.core.occupancy_map import OccupancyMap  # noqa: E402
from localization.ros import cdr, messages
from localization.ros.conversions import pose_from_msg, stamp_to_sec  # noqa: E402
from localization.ros.stamps import StampBook  # noqa: E402


def test_odometry_msg_carries_pose_covariance_frames_and_stamp():
    cov = np.array([[0.04, 0.01, 0.0], [0.01, 0.09, 0.002], [0.0, 0.002, 0.01]])
    msg = messages.odometry_msg([1.0, -2.0, 3.0], cov, Time(sec=5, nanosec=7), "map", "base_link_pf")
    assert (msg.header.frame_id, msg.child_frame_id) == ("map", "base_link_pf")
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (5, 7)
    np.testing.assert_allclose(pose_from_msg(msg.pose.pose), [1.0, -2.0, 3.0], atol=1e-12)
    c6 = np.array(msg.pose.covariance).reshape(6, 6)
    np.testing.assert_allclose(c6[np.ix_([0, 1, 5], [0, 1, 5])], cov)
    assert c6[2, 2] == c6[3, 3] == c6[4, 4] == 0.0


@pytest.mark.parametrize("bad", [[math.nan, 0.0, 0.0], [0.0, math.inf, 0.0], [0.0, 0.0, -math.inf]])
def test_non_finite_pose_gives_no_message(bad):
    assert messages.odometry_msg(bad, np.eye(3), 1.0, "map", "b") is None
    assert messages.transform_msg(bad, 1.0, "map", "b") is None


def test_non_finite_covariance_is_published_as_unknown():
    msg = messages.odometry_msg([0.0, 0.0, 0.0], np.full((3, 3), np.nan), 1.0, "map", "b")
    c6 = np.array(msg.pose.covariance).reshape(6, 6)
    assert np.all(np.isfinite(c6))
    assert c6[0, 0] == c6[1, 1] == c6[5, 5] == messages.UNKNOWN_VARIANCE


def pose_array(particles, stamp, frame_id, max_count) -> PoseArray:
    return deserialize_message(cdr.pose_array_cdr(particles, stamp, frame_id, max_count), PoseArray)


def test_pose_array_drops_non_finite_particles_and_caps_the_count():
    particles = np.column_stack([np.arange(1000.0), np.zeros(1000), np.zeros(1000)])
    particles[10] = [np.nan, 0, 0]
    msg = pose_array(particles, 2.5, "map", 100)
    assert msg.header.frame_id == "map" and len(msg.poses) == 100
    xs = [p.position.x for p in msg.poses]
    assert all(math.isfinite(x) for x in xs) and xs[0] == 0.0 and xs[-1] == 999.0  # spread over the cloud
    assert len(pose_array(particles[:50], 2.5, "map", 100).poses) == 49  # the NaN one dropped
    assert pose_array(particles, 2.5, "map", 0).poses == []


@pytest.mark.parametrize("frame_id", ["", "m", "map", "odom_", "a_longer_frame"])  # every string padding
@pytest.mark.parametrize("count", [0, 1, 7])
def test_pose_array_cdr_matches_rclpy_serialization(frame_id, count):
    rng = np.random.default_rng(count)
    particles = rng.uniform(-50, 50, (count, 3))
    expected = PoseArray()
    expected.header.stamp = Time(sec=1_700_000_123, nanosec=456_789_012)
    expected.header.frame_id = frame_id
    for x, y, th in particles:
        pose = Pose()
        pose.position.x, pose.position.y = float(x), float(y)
        pose.orientation.z, pose.orientation.w = math.sin(th / 2), math.cos(th / 2)
        expected.poses.append(pose)
    raw = cdr.pose_array_cdr(particles, Time(sec=1_700_000_123, nanosec=456_789_012), frame_id, 100)
    # rclpy leaves its alignment padding uninitialised: compare the length and the decoded message
    assert len(raw) == len(serialize_message(expected))
    assert deserialize_message(raw, PoseArray) == expected
def test_transform_msg():
    t = messages.transform_msg([2.0, 3.0, -1.0], 4.25, "map", "base_link_pf")
    assert (t.header.frame_id, t.child_frame_id) == ("map", "base_link_pf")
    assert stamp_to_sec(t.header.stamp) == 4.25
    assert (t.transform.translation.x, t.transform.translation.y, t.transform.translation.z) == (2.0, 3.0, 0.0)
    q = t.transform.rotation
    assert math.isclose(2 * math.atan2(q.z, q.w), -1.0)


def test_map_to_odom_composes_back_to_the_estimate():
    estimate, odom = np.array([4.0, -1.0, 2.5]), np.array([1.5, 0.3, -0.7])
    m2o = messages.map_to_odom(estimate, odom)
    np.testing.assert_allclose(compose(m2o, odom), estimate, atol=1e-12)
    np.testing.assert_allclose(messages.map_to_odom(odom, odom), [0, 0, 0], atol=1e-12)


def test_time_msg_and_stamp_book_keep_exact_nanoseconds():
    assert messages.time_msg(math.nan).sec == 0 and messages.time_msg(-1.0).sec == 0
    book = StampBook(size=2)
    exact = Time(sec=1_700_000_000, nanosec=123_456_789)
    t = book.remember(exact)
    assert book.lookup(t) == (exact.sec, exact.nanosec)
    assert book.remember((exact.sec, exact.nanosec)) == t  # a (sec, nanosec) pair (ros.cdr's readers) alike
    book.remember(Time(sec=1, nanosec=0))
    book.remember(Time(sec=2, nanosec=0))  # evicts the oldest
    sec, nanosec = book.lookup(t)  # falls back to the float, which cannot hold every nanosecond
    assert sec == exact.sec and abs(nanosec - exact.nanosec) < 1000


def test_occupancy_grid_msg_round_trips():
    data = np.full((4, 6), -1, dtype=np.int8)
    data[1:3, 1:5] = 0
    data[0, 0] = 100
    m = OccupancyMap(data, 0.05, (1.0, 2.0, 0.5), "map")
    back = OccupancyMap.from_msg(messages.occupancy_grid_msg(m))
    np.testing.assert_array_equal(back.data, data)
    assert back.resolution == 0.05 and np.allclose(back.origin, m.origin) and back.frame_id == "map"


@pytest.mark.parametrize("sec, nanosec, expected", [
    (3_491_151_709, 782_864_170, (2**31 - 1, 999_999_999)),  # beyond int32 (a fuzzed header stamp)
    (-5, 10, (0, 10)),
    (12, 5_000_000_000, (12, 999_999_999)),
    (12, 34, (12, 34)),
])
def test_out_of_range_stamps_are_clamped_to_what_can_be_serialized(sec, nanosec, expected):
    stamp = Time()
    stamp.sec, stamp.nanosec = sec, nanosec  # rclpy's Python message takes it without a check
    t = messages.time_msg(stamp)
    assert (t.sec, t.nanosec) == expected
    raw = cdr.pose_array_cdr(np.zeros((2, 3)), stamp, "map", 10)
    assert deserialize_message(raw, PoseArray).header.stamp == t
    serialize_message(messages.odometry_msg([0.0, 0.0, 0.0], np.eye(3), stamp, "map", "b"))  # does not raise


CDR_CASES = [  # pose, covariance, stamp, frame ids of 0-9 characters (every string padding)
    ([1.0, -2.0, 3.0], np.array([[0.04, 0.01, 0.0], [0.01, 0.09, 0.002], [0.0, 0.002, 0.01]]),
     Time(sec=1648582000, nanosec=123456789), "map", "base_link_pf"),
    ([-41.25, 0.0, -math.pi], np.full((3, 3), np.nan), 1648582000.987654, "", "b"),
    ([1e5, -1e-9, 0.5], None, -3.0, "ma", "odom"),
    ([0.0, 0.0, 0.0], np.eye(2), 3e10, "map_frm", "laser_bl"),
    ([2.5, 7.0, 1.0], np.diag([1.0, 2.0, math.inf]), Time(sec=5, nanosec=7), "abcdefghi", "x" * 9),
]


@pytest.mark.parametrize("pose, cov, stamp, frame, child", CDR_CASES)
def test_serialized_outputs_equal_rclpy_serialization_of_the_built_messages(pose, cov, stamp, frame, child):
    from geometry_msgs.msg import PoseWithCovarianceStamped, TransformStamped  # noqa: F401
    from nav_msgs.msg import Odometry  # noqa: F401
    from tf2_msgs.msg import TFMessage

    pairs = [(cdr.odometry_cdr(pose, cov, stamp, frame, child), messages.odometry_msg(pose, cov, stamp, frame, child)),
             (cdr.pose_with_covariance_cdr(pose, cov, stamp, frame),
              messages.pose_with_covariance_msg(pose, cov, stamp, frame)),
             (cdr.tf_message_cdr(pose, stamp, frame, child),
              TFMessage(transforms=[messages.transform_msg(pose, stamp, frame, child)]))]
    for raw, msg in pairs:
        # the same length and every field equal (rclpy leaves its alignment padding uninitialised)
        assert len(raw) == len(serialize_message(msg))
        assert deserialize_message(raw, type(msg)) == msg


@pytest.mark.parametrize("bad", [[math.nan, 0.0, 0.0], [0.0, math.inf, 0.0], [0.0, 0.0, -math.inf]])
def test_serialized_outputs_of_a_non_finite_pose_are_none(bad):
    assert cdr.odometry_cdr(bad, np.eye(3), 1.0, "map", "b") is None
    assert cdr.pose_with_covariance_cdr(bad, np.eye(3), 1.0, "map") is None
    assert cdr.tf_message_cdr(bad, 1.0, "map", "b") is None
