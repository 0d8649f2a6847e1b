"""The node's CDR readers (``ros.cdr.read_odometry``, ``read_scan``): the values ``ros.conversions`` gives of
rclpy's deserialized message, bit for bit, in both byte orders; bytes that are not one raise ``CdrError``."""
from __future__ import annotations

import math
import struct

import numpy as np
import pytest

pytest.importorskip("nav_msgs.msg")

from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from sensor_msgs.msg import LaserScan  # noqa: E402

from localization.ros.cdr import CdrError, read_odometry, read_scan  # noqa: E402
from localization.ros.conversions import odometry_from_msg, scan_from_msg  # noqa: E402

FRAMES = ["", "o", "odom", "base_link_pf", "ümlaut_frame"]  # every alignment after the string


def _odometry(rng, frame: str, child: str) -> Odometry:
    msg = Odometry()
    msg.header.stamp.sec, msg.header.stamp.nanosec = int(rng.integers(0, 2**31)), int(rng.integers(0, 10**9))
    msg.header.frame_id, msg.child_frame_id = frame, child
    p = msg.pose.pose
    p.position.x, p.position.y, p.position.z = (float(v) for v in rng.normal(0, 50, 3))
    q = rng.normal(size=4)
    p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = (float(v) for v in q / np.linalg.norm(q))
    msg.pose.covariance = rng.normal(size=36)
    t = msg.twist.twist
    t.linear.x, t.linear.y, t.linear.z, t.angular.x, t.angular.y, t.angular.z = (float(v) for v in rng.normal(0, 3, 6))
    msg.twist.covariance = rng.normal(size=36)
    return msg


def _scan(rng, frame: str, count: int) -> LaserScan:
    msg = LaserScan()
    msg.header.stamp.sec, msg.header.stamp.nanosec = int(rng.integers(0, 2**31)), int(rng.integers(0, 10**9))
    msg.header.frame_id = frame
    (msg.angle_min, msg.angle_max, msg.angle_increment, msg.time_increment, msg.scan_time, msg.range_min,
     msg.range_max) = (float(np.float32(v)) for v in rng.normal(0, 3, 7))
    ranges = rng.uniform(0, 30, count).astype(np.float32)
    ranges[::7] = np.inf
    ranges[3::11] = np.nan
    msg.ranges = ranges.tolist()
    msg.intensities = rng.uniform(0, 1, count // 2).astype(np.float32).tolist()
    return msg


def _big_endian(raw: bytes, layout) -> bytes:
    """The same message in big-endian CDR: ``layout`` lists its fields in order ('i'/'I'/'f'/'d' with a count,
    's' a string, 'F' a float sequence), each aligned as CDR aligns it."""
    out, pos = bytearray(b"\x00\x00\x00\x00"), 4

    def align(n):
        nonlocal pos
        pad = -(pos - 4) % n
        out.extend(raw[pos:pos + pad])
        pos += pad

    def swap(fmt, count):
        nonlocal pos
        size = struct.calcsize(fmt)
        align(size)
        for _ in range(count):
            out.extend(struct.pack(">" + fmt, *struct.unpack_from("<" + fmt, raw, pos)))
            pos += size
    for kind, count in layout:
        if kind == "s":
            swap("I", 1)
            size = struct.unpack_from(">I", out, len(out) - 4)[0]
            out.extend(raw[pos:pos + size])
            pos += size
        elif kind == "F":
            swap("I", 1)
            swap("f", struct.unpack_from(">I", out, len(out) - 4)[0])
        else:
            swap(kind, count)
    return bytes(out + raw[pos:])


def _same_bits(a, b) -> bool:
    return np.asarray(a, dtype=float).tobytes() == np.asarray(b, dtype=float).tobytes()


@pytest.mark.parametrize("frame", FRAMES)
@pytest.mark.parametrize("child", FRAMES[:3])
def test_read_odometry_equals_the_converted_message(frame, child):
    rng = np.random.default_rng(len(frame) * 7 + len(child))
    msg = _odometry(rng, frame, child)
    raw = serialize_message(msg)
    want = odometry_from_msg(deserialize_message(raw, Odometry))
    layout = [("i", 1), ("I", 1), ("s", 1), ("s", 1), ("d", 7 + 36 + 6 + 36)]
    for data in (raw, _big_endian(raw, layout)):
        got = read_odometry(data)
        assert got.stamp == want.stamp == (msg.header.stamp.sec, msg.header.stamp.nanosec)
        assert got.twist == want.twist
        assert _same_bits(got.pose, want.pose)


@pytest.mark.parametrize("frame", FRAMES)
@pytest.mark.parametrize("count", [0, 1, 2, 1081])
def test_read_scan_equals_the_converted_message(frame, count):
    rng = np.random.default_rng(count + len(frame))
    raw = serialize_message(_scan(rng, frame, count))
    back = deserialize_message(raw, LaserScan)
    want = scan_from_msg(back)
    layout = [("i", 1), ("I", 1), ("s", 1), ("f", 7), ("F", 1), ("F", 1)]
    for data in (raw, memoryview(raw), _big_endian(raw, layout)):
        stamp, got = read_scan(data)
        assert stamp == (back.header.stamp.sec, back.header.stamp.nanosec)
        assert _same_bits(got.ranges, want.ranges) and got.ranges.dtype == want.ranges.dtype
        for field in ("stamp", "angle_min", "angle_max", "angle_increment", "range_min", "range_max",
                      "time_increment", "scan_time", "frame_id"):
            assert getattr(got, field) == getattr(want, field) or (
                math.isnan(getattr(got, field)) and math.isnan(getattr(want, field))), field


@pytest.mark.parametrize("cut", [0, 3, 4, 9, 20, 60, -1])
def test_truncated_or_foreign_bytes_raise_cdr_error(cut):
    rng = np.random.default_rng(0)
    scan = serialize_message(_scan(rng, "laser", 100))
    odom = serialize_message(_odometry(rng, "odom", "base_link"))
    with pytest.raises(CdrError):
        read_scan(scan[:cut] if cut >= 0 else scan[:-1])  # -1: the intensities cut short
    with pytest.raises(CdrError):
        read_odometry(odom[:cut] if cut >= 0 else odom[:-1])
    for foreign in (b"\x00\x07\x00\x00" + scan[4:], b"\x01\x01\x00\x00" + odom[4:]):  # XCDR2, not CDR
        with pytest.raises(CdrError, match="not plain CDR"):
            (read_scan if len(foreign) == len(scan) else read_odometry)(foreign)
