"""The node's per-message inputs and outputs in CDR directly, without building a Python message.

On every odometry message the node publishes nav_msgs/Odometry and a TF, on every scan a
PoseWithCovarianceStamped and the particle cloud (PoseArray): building those as rclpy message objects
(nested Python objects, 36-float covariance lists, a Pose per particle) and having rclpy convert them
costs more than composing the pose. These functions write the same bytes with ``struct`` and numpy;
the node publishes them as they are (``publisher.publish(bytes)``). Each deserialises to the message
``localization.ros.messages`` builds for the same input (test_messages.py), and returns None where that
builder does (a non-finite pose).

The inputs at their rates (odometry ~50 Hz, scans ~40 Hz) are read the same way: ``read_odometry`` and
``read_scan`` take a subscription's CDR bytes to what the node needs (``conversions.OdometryIn``, a
``ScanData`` and its exact stamp): the values ``ros.conversions`` gives of rclpy's message, bit for bit
(test_cdr.py).

CDR (XCDR1): the 4-byte encapsulation header (00 01 00 00 little endian, 00 00 00 00 big endian; written
little endian), then every field aligned to its own size counted from the end of that header; a string
is a uint32 length (with the NUL), its bytes and the NUL; a sequence a uint32 count and its elements.
"""
from __future__ import annotations

import struct

import numpy as np

from localization.core.geometry import quaternion_to_yaw
from localization.core.odometry import TwistData
from localization.core.scan import ScanData
from localization.ros.conversions import OdometryIn, parts_to_sec
from localization.ros.messages import covariance_6x6_array, finite_pose, select_particles
from localization.ros.stamps import stamp_parts

ENCAPSULATION = b"\x00\x01\x00\x00"  # CDR, little endian
_ZERO_TWIST = bytes(8 * (6 + 36))  # geometry_msgs/TwistWithCovariance: all zero


def _padding(offset: int, size: int) -> int:
    """Bytes before a field of ``size`` at byte ``offset`` of the message (alignment counts from the end of the
    encapsulation header)."""
    return -(offset - 4) % size


def _align(buf: bytearray, size: int) -> None:
    buf += bytes(_padding(len(buf), size))


def _string(buf: bytearray, text: str) -> None:
    data = text.encode()
    _align(buf, 4)
    buf += struct.pack("<I", len(data) + 1) + data + b"\0"


def _header(buf: bytearray, stamp, frame_id: str) -> None:
    """std_msgs/Header: builtin_interfaces/Time (int32 sec, uint32 nanosec), frame_id."""
    _align(buf, 4)
    buf += struct.pack("<iI", *stamp_parts(stamp))
    _string(buf, frame_id)


def _pose(buf: bytearray, pose: np.ndarray) -> None:
    """geometry_msgs/Pose (or a Transform: the same 7 float64) of a planar pose [x, y, yaw]."""
    half = 0.5 * float(pose[2])
    _align(buf, 8)
    buf += struct.pack("<7d", float(pose[0]), float(pose[1]), 0.0, 0.0, 0.0, np.sin(half), np.cos(half))


def _stamped_pose(pose, covariance, stamp, frame_id: str, child_frame_id: str | None = None) -> bytearray | None:
    """Header, (child frame id,) geometry_msgs/PoseWithCovariance: the start of an Odometry or a
    PoseWithCovarianceStamped; None if the pose is not finite."""
    pose = finite_pose(pose)
    if pose is None:
        return None
    buf = bytearray(ENCAPSULATION)
    _header(buf, stamp, frame_id)
    if child_frame_id is not None:
        _string(buf, child_frame_id)
    _pose(buf, pose)
    buf += covariance_6x6_array(covariance).astype("<f8").tobytes()
    return buf


def odometry_cdr(pose, covariance, stamp, frame_id: str, child_frame_id: str) -> bytes | None:
    """nav_msgs/Odometry of ``messages.odometry_msg``, serialized; None if the pose is not finite."""
    buf = _stamped_pose(pose, covariance, stamp, frame_id, child_frame_id)
    return None if buf is None else bytes(buf + _ZERO_TWIST)


def pose_with_covariance_cdr(pose, covariance, stamp, frame_id: str) -> bytes | None:
    """geometry_msgs/PoseWithCovarianceStamped of ``messages.pose_with_covariance_msg``, serialized;
    None if the pose is not finite."""
    buf = _stamped_pose(pose, covariance, stamp, frame_id)
    return None if buf is None else bytes(buf)


def tf_message_cdr(pose, stamp, parent_frame: str, child_frame: str) -> bytes | None:
    """tf2_msgs/TFMessage holding the one transform ``messages.transform_msg`` builds, serialized;
    None if the pose is not finite."""
    pose = finite_pose(pose)
    if pose is None:
        return None
    buf = bytearray(ENCAPSULATION) + struct.pack("<I", 1)
    _header(buf, stamp, parent_frame)
    _string(buf, child_frame)
    _pose(buf, pose)
    return bytes(buf)


def pose_array_cdr(particles, stamp, frame_id: str, max_count: int) -> bytes:
    """geometry_msgs/PoseArray of (at most ``max_count``, ``messages.select_particles``) particles,
    serialized: the header, the pose count, then per pose 7 float64 (position x, y, z, orientation x, y,
    z, w) written with numpy in one array."""
    p = select_particles(particles, max_count)
    buf = bytearray(ENCAPSULATION)
    _header(buf, stamp, frame_id)
    _align(buf, 4)
    buf += struct.pack("<I", len(p))
    if len(p):
        _align(buf, 8)
    poses = np.zeros((len(p), 7), dtype="<f8")
    poses[:, 0:2] = p[:, 0:2]
    poses[:, 5] = np.sin(0.5 * p[:, 2])
    poses[:, 6] = np.cos(0.5 * p[:, 2])
    return bytes(buf) + poses.tobytes()


class CdrError(ValueError):
    """Bytes that are not the expected message in plain CDR (truncated, or another encoding)."""


class _Reader:
    """Fields read in order from CDR bytes, each aligned to its size (the module docstring)."""

    def __init__(self, data):
        if len(data) < 4 or data[0] != 0 or data[1] not in (0, 1):
            raise CdrError(f"not plain CDR (encapsulation {bytes(data[:4]).hex() or 'missing'})")
        self.data, self.pos, self.order = data, 4, "<" if data[1] == 1 else ">"

    def take(self, fmt: str, align: int) -> tuple:
        self.pos += _padding(self.pos, align)
        fmt = self.order + fmt
        try:
            values = struct.unpack_from(fmt, self.data, self.pos)
        except struct.error:
            raise CdrError(f"truncated at byte {self.pos} of {len(self.data)}") from None
        self.pos += struct.calcsize(fmt)
        return values

    def skip(self, size: int, align: int) -> None:
        """Past a field of ``size`` bytes (aligned to ``align``) that is not needed, checking it is there."""
        self.pos += _padding(self.pos, align) + size
        if self.pos > len(self.data):
            raise CdrError(f"truncated: {self.pos} bytes needed, {len(self.data)} given")

    def string(self) -> str:
        (size,) = self.take("I", 4)  # with the NUL
        end = self.pos + size
        if end > len(self.data):
            raise CdrError(f"a string of {size} bytes runs past the end ({len(self.data)})")
        text = bytes(self.data[self.pos:max(end - 1, self.pos)]).decode(errors="replace")
        self.pos = end
        return text

    def floats(self) -> np.ndarray:
        """A sequence<float32> as float64."""
        (count,) = self.take("I", 4)
        if self.pos + 4 * count > len(self.data):
            raise CdrError(f"a sequence of {count} floats runs past the end ({len(self.data)} bytes)")
        values = np.frombuffer(self.data, dtype=self.order + "f4", count=count, offset=self.pos)
        self.pos += 4 * count
        return values.astype(float)

    def stamp(self) -> tuple[int, int]:
        """builtin_interfaces/Time: (sec, nanosec)."""
        return self.take("iI", 4)


def read_odometry(data) -> OdometryIn:
    """nav_msgs/Odometry's CDR bytes -> ``OdometryIn`` (``conversions.odometry_from_msg`` of the message);
    ``CdrError`` for bytes that are not one."""
    r = _Reader(data)
    stamp = r.stamp()
    frame_id = r.string()
    r.string()  # child_frame_id
    x, y, _, qx, qy, qz, qw = r.take("7d", 8)
    r.skip(36 * 8, 8)  # the pose's covariance
    vx, vy, _, _, _, wz = r.take("6d", 8)
    r.skip(36 * 8, 8)  # the twist's
    pose = np.array([float(x), float(y), float(quaternion_to_yaw(qx, qy, qz, qw))])
    return OdometryIn(stamp, TwistData(stamp=parts_to_sec(*stamp), vx=vx, vy=vy, wz=wz, frame_id=frame_id), pose)


def read_scan(data) -> tuple[tuple[int, int], ScanData]:
    """sensor_msgs/LaserScan's CDR bytes -> (its exact stamp, ``conversions.scan_from_msg`` of the message);
    ``CdrError`` for bytes that are not one."""
    r = _Reader(data)
    stamp = r.stamp()
    frame_id = r.string()
    angle_min, angle_max, angle_increment, time_increment, scan_time, range_min, range_max = r.take("7f", 4)
    ranges = r.floats()
    (count,) = r.take("I", 4)
    r.skip(4 * count, 4)  # the intensities
    return stamp, ScanData(stamp=parts_to_sec(*stamp), ranges=ranges, angle_min=angle_min, angle_max=angle_max,
                           angle_increment=angle_increment, range_min=range_min, range_max=range_max,
                           time_increment=time_increment, scan_time=scan_time, frame_id=frame_id)
