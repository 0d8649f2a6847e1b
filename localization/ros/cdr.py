"""The node's per-message outputs serialized directly (CDR), without building a Python message.

On every odometry message the node publishes nav_msgs/Odometry and a TF, on every scan a
PoseWithCovarianceStamped and the particle cloud (PoseArray): building those as rclpy message objects
(nested Python objects, 36-float covariance lists, a Pose per particle) and having rclpy convert them
costs more than composing the pose. These functions write the same bytes with ``struct`` and numpy;
the node publishes them as they are (``publisher.publish(bytes)``). Each deserialises to the message
``localization.ros.messages`` builds for the same input (test_messages.py), and returns None where that
builder does (a non-finite pose).

CDR (XCDR1, little endian): the 4-byte encapsulation header 00 01 00 00, then every field aligned to
its own size counted from the end of that header; a string is a uint32 length (with the NUL), its
bytes and the NUL; a sequence a uint32 count and its elements.
"""
from __future__ import annotations

import struct

import numpy as np

from localization.ros.messages import covariance_6x6_array, finite_pose, select_particles
from localization.ros.stamps import stamp_parts

ENCAPSULATION = b"\x00\x01\x00\x00"  # CDR, little endian
_ZERO_TWIST = bytes(8 * (6 + 36))  # geometry_msgs/TwistWithCovariance: all zero


def _align(buf: bytearray, size: int) -> None:
    buf += bytes(-(len(buf) - 4) % size)


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
