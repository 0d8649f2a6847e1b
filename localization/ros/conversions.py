"""ROS message -> core converters. Duck-typed: they read fields only, so they accept rclpy
messages and the rosbags-deserialised messages of the replay tool alike (no ROS import)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from localization.core.geometry import quaternion_to_yaw
from localization.core.odometry import TwistData
from localization.core.scan import ScanData


@dataclass
class PoseData:
    stamp: float
    frame_id: str
    pose: np.ndarray  # (3,)
    covariance: np.ndarray | None  # (3, 3) over x, y, θ, or None


def stamp_to_sec(stamp) -> float:
    """builtin_interfaces/Time -> seconds (float)."""
    return parts_to_sec(stamp.sec, stamp.nanosec)


def parts_to_sec(sec: int, nanosec: int) -> float:
    """(sec, nanosec) -> seconds (float)."""
    return float(sec) + 1e-9 * float(nanosec)


def sec_to_stamp_parts(t: float) -> tuple[int, int]:
    """Seconds -> (sec, nanosec), nanosec in [0, 1e9)."""
    total = int(round(t * 1e9))
    return total // 1_000_000_000, total % 1_000_000_000


def scan_from_msg(msg) -> ScanData:
    return ScanData(stamp=stamp_to_sec(msg.header.stamp), ranges=np.asarray(msg.ranges, dtype=float),
                    angle_min=float(msg.angle_min), angle_max=float(msg.angle_max),
                    angle_increment=float(msg.angle_increment), range_min=float(msg.range_min),
                    range_max=float(msg.range_max), time_increment=float(msg.time_increment),
                    scan_time=float(msg.scan_time), frame_id=msg.header.frame_id)


def twist_from_odometry(msg) -> TwistData:
    t = msg.twist.twist
    return TwistData(stamp=stamp_to_sec(msg.header.stamp), vx=float(t.linear.x), vy=float(t.linear.y),
                     wz=float(t.angular.z), frame_id=msg.header.frame_id)


class OdometryIn(NamedTuple):
    """What the node reads of a nav_msgs/Odometry: its exact stamp, its twist and its pose [x, y, yaw]."""

    stamp: tuple[int, int]  # (sec, nanosec)
    twist: TwistData
    pose: np.ndarray


def odometry_from_msg(msg) -> OdometryIn:
    """nav_msgs/Odometry -> ``OdometryIn`` (``ros.cdr.read_odometry`` reads the same from its bytes)."""
    return OdometryIn((int(msg.header.stamp.sec), int(msg.header.stamp.nanosec)), twist_from_odometry(msg),
                      pose_from_msg(msg.pose.pose))


def pose_from_msg(pose) -> np.ndarray:
    """geometry_msgs/Pose -> [x, y, yaw]."""
    q = pose.orientation
    return np.array([float(pose.position.x), float(pose.position.y), float(quaternion_to_yaw(q.x, q.y, q.z, q.w))])


def pose_from_pose_with_covariance(msg) -> PoseData:
    """geometry_msgs/PoseWithCovarianceStamped -> pose and the 3×3 (x, y, yaw) covariance."""
    cov6 = np.asarray(msg.pose.covariance, dtype=float)
    cov = None
    if cov6.size == 36:
        full = cov6.reshape(6, 6)
        cov = full[np.ix_([0, 1, 5], [0, 1, 5])]
    return PoseData(stamp_to_sec(msg.header.stamp), msg.header.frame_id, pose_from_msg(msg.pose.pose), cov)
