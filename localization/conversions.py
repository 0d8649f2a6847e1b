"""ROS message -> core converters. Duck-typed: they read fields only, so they accept rclpy
messages and the rosbags-deserialised messages of the replay tool alike (no ROS import)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .geometry import quaternion_to_yaw


@dataclass
class ScanData:
    stamp: float
    frame_id: str
    ranges: np.ndarray
    angle_min: float
    angle_max: float
    angle_increment: float
    range_min: float
    range_max: float


@dataclass
class TwistData:
    stamp: float
    frame_id: str
    vx: float
    vy: float
    wz: float


@dataclass
class PoseData:
    stamp: float
    frame_id: str
    pose: np.ndarray  # (3,)
    covariance: np.ndarray | None  # (3, 3) over x, y, θ, or None


def stamp_to_sec(stamp) -> float:
    """builtin_interfaces/Time -> seconds (float)."""
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def sec_to_stamp_parts(t: float) -> tuple[int, int]:
    """Seconds -> (sec, nanosec), nanosec in [0, 1e9)."""
    total = int(round(t * 1e9))
    return total // 1_000_000_000, total % 1_000_000_000


def scan_from_msg(msg) -> ScanData:
    return ScanData(stamp_to_sec(msg.header.stamp), msg.header.frame_id,
                    np.asarray(msg.ranges, dtype=float), float(msg.angle_min), float(msg.angle_max),
                    float(msg.angle_increment), float(msg.range_min), float(msg.range_max))


def twist_from_odometry(msg) -> TwistData:
    t = msg.twist.twist
    return TwistData(stamp_to_sec(msg.header.stamp), msg.header.frame_id,
                     float(t.linear.x), float(t.linear.y), float(t.angular.z))


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


def is_finite_pose(pose) -> bool:
    return bool(np.all(np.isfinite(np.asarray(pose, dtype=float))))


def finite_or(value: float, fallback: float = 0.0) -> float:
    return value if math.isfinite(value) else fallback
