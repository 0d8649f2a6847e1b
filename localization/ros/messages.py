"""Core -> ROS message builders for the node's outputs (and a map message for tests/simulators).

They import the message packages but not rclpy, and never emit a NaN or an infinity:

* ``odometry_msg`` / ``transform_msg`` return ``None`` for a non-finite pose (the caller skips
  publishing); a non-finite covariance becomes "unknown" (``UNKNOWN_VARIANCE`` on the diagonal);
* ``select_particles`` drops non-finite particles and draws at most ``max_count`` of them (for the
  cloud, which ``ros.cdr.pose_array_cdr`` serializes).

Stamps are ``builtin_interfaces/Time`` messages or float seconds (see ``time_msg``).
"""
from __future__ import annotations

import array
import math

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Pose, PoseWithCovarianceStamped, Quaternion, TransformStamped
from nav_msgs.msg import OccupancyGrid, Odometry
from std_msgs.msg import Float32

from localization.core.geometry import compose, inverse, yaw_to_quaternion
from localization.core.occupancy_map import OccupancyMap
from localization.ros.stamps import time_msg

UNKNOWN_VARIANCE = 1e6  # what a non-finite covariance is published as
COV_INDEX = (0, 1, 5)  # x, y, yaw rows/columns of a 6x6 ROS pose covariance
_COV_FLAT = np.array([6 * i + j for i in COV_INDEX for j in COV_INDEX])  # their 9 places in the flat 36


def finite_pose(pose) -> np.ndarray | None:
    pose = np.asarray(pose, dtype=float).reshape(-1)
    if pose.size != 3 or not all(math.isfinite(v) for v in pose.tolist()):
        return None
    return pose


def pose_msg(pose) -> Pose:
    """geometry_msgs/Pose of a finite planar pose [x, y, yaw]."""
    x, y, yaw = (float(v) for v in pose)
    qx, qy, qz, qw = (float(v) for v in yaw_to_quaternion(yaw))
    msg = Pose()
    msg.position.x, msg.position.y, msg.position.z = x, y, 0.0
    msg.orientation = Quaternion(x=qx, y=qy, z=qz, w=qw)
    return msg


def covariance_6x6(covariance) -> list[float]:
    """The 3×3 (x, y, yaw) covariance as a row-major 6×6 ROS covariance (other entries 0).
    Non-finite input (or the wrong shape) becomes ``UNKNOWN_VARIANCE`` on the x, y, yaw diagonal."""
    return [float(v) for v in covariance_6x6_array(covariance)]


def covariance_6x6_array(covariance) -> np.ndarray:
    """``covariance_6x6`` as a flat float64 array of 36."""
    out = np.zeros(36)
    cov = None if covariance is None else np.asarray(covariance, dtype=float)
    if cov is None or cov.shape != (3, 3) or not np.isfinite(cov).all():
        out[_COV_FLAT[::4]] = UNKNOWN_VARIANCE  # the x, y, yaw diagonal
    else:
        out[_COV_FLAT] = (0.5 * (cov + cov.T)).ravel()
    return out


def _stamped(msg, pose, covariance, stamp, frame_id: str):
    """Fill ``msg`` (Odometry or PoseWithCovarianceStamped: both carry a PoseWithCovariance in
    ``.pose``) with the estimate; None if the pose is not finite."""
    pose = finite_pose(pose)
    if pose is None:
        return None
    msg.header.stamp = time_msg(stamp)
    msg.header.frame_id = frame_id
    msg.pose.pose = pose_msg(pose)
    msg.pose.covariance = covariance_6x6(covariance)
    return msg


def odometry_msg(pose, covariance, stamp, frame_id: str, child_frame_id: str) -> Odometry | None:
    """nav_msgs/Odometry carrying the estimate (twist left zero); None if the pose is not finite."""
    msg = _stamped(Odometry(), pose, covariance, stamp, frame_id)
    if msg is not None:
        msg.child_frame_id = child_frame_id
    return msg


def pose_with_covariance_msg(pose, covariance, stamp, frame_id: str) -> PoseWithCovarianceStamped | None:
    """geometry_msgs/PoseWithCovarianceStamped of the estimate (nav2_amcl's /amcl_pose); None if not finite."""
    return _stamped(PoseWithCovarianceStamped(), pose, covariance, stamp, frame_id)


def diagnostic_array_msg(status, stamp, name: str, hardware_id: str = "") -> DiagnosticArray:
    """diagnostic_msgs/DiagnosticArray with one DiagnosticStatus from a ``core.watchdog.Status``."""
    msg = DiagnosticArray()
    msg.header.stamp = time_msg(stamp)
    level = int(min(max(status.level, 0), 3))
    item = DiagnosticStatus(level=level.to_bytes(1, "little"), name=name, message=str(status.message),
                            hardware_id=hardware_id)
    item.values = [KeyValue(key=str(k), value=str(v)) for k, v in status.values.items()]
    msg.status = [item]
    return msg


def select_particles(particles, max_count: int) -> np.ndarray:
    """The finite rows of ``particles`` (N, 3), thinned to at most ``max_count`` evenly spaced ones."""
    p = np.asarray(particles, dtype=float).reshape(-1, 3)
    if not np.isfinite(p).all():  # one flat pass; the per-row test only when a row is bad
        p = p[np.isfinite(p).all(axis=1)]
    if max_count <= 0:
        return p[:0]
    if len(p) > max_count:
        p = p[np.linspace(0, len(p) - 1, max_count).round().astype(np.intp)]
    return p


def transform_msg(pose, stamp, parent_frame: str, child_frame: str) -> TransformStamped | None:
    """geometry_msgs/TransformStamped parent -> child for a planar pose; None if not finite."""
    pose = finite_pose(pose)
    if pose is None:
        return None
    p = pose_msg(pose)
    msg = TransformStamped()
    msg.header.stamp = time_msg(stamp)
    msg.header.frame_id = parent_frame
    msg.child_frame_id = child_frame
    msg.transform.translation.x = p.position.x
    msg.transform.translation.y = p.position.y
    msg.transform.translation.z = 0.0
    msg.transform.rotation = p.orientation
    return msg


def map_to_odom(estimate_pose, odom_pose) -> np.ndarray:
    """The map -> odom transform (REP-105) that makes map -> odom -> base_link equal the estimate:
    ``estimate ⊕ inverse(odom pose)``, both poses taken at the same time."""
    return compose(np.asarray(estimate_pose, dtype=float), inverse(np.asarray(odom_pose, dtype=float)))


def health_msg(health: float) -> Float32 | None:
    """std_msgs/Float32 of the filter health in [0, 1] (``/pf/health``); None when not finite."""
    h = float(health)
    if not np.isfinite(h):
        return None
    return Float32(data=min(max(h, 0.0), 1.0))


def occupancy_grid_msg(occupancy_map: OccupancyMap, stamp=0.0, frame_id: str | None = None) -> OccupancyGrid:
    """nav_msgs/OccupancyGrid of a map (what map_server would publish)."""
    msg = OccupancyGrid()
    msg.header.stamp = time_msg(stamp)
    msg.header.frame_id = frame_id or occupancy_map.frame_id
    msg.info.map_load_time = time_msg(stamp)
    msg.info.resolution = float(occupancy_map.resolution)
    msg.info.width = int(occupancy_map.width)
    msg.info.height = int(occupancy_map.height)
    msg.info.origin = pose_msg(occupancy_map.origin)
    msg.data = array.array("b", np.ascontiguousarray(occupancy_map.data, dtype=np.int8).tobytes())
    return msg
