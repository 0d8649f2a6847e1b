"""The ``particle_filter`` ROS 2 node: wiring only (ROS messages -> converters -> Localizer ->
message builders -> ROS messages). See docs/node.md for topics, frames and parameters.

    ros2 run localization particle_filter --ros-args --params-file config/params.yaml
    python -m localization.particle_filter --ros-args -p num_particles:=500

Threading: a SingleThreadedExecutor runs every subscription callback (each is short); the scan
callback only leaves the message in the one-slot mailbox of the sensor-update thread
(``scan_worker.LatestScanWorker``), which runs the sensor update and publishes its outputs. So a
slow sensor update never delays the pose published on odometry (the Localizer queues odometry
that arrives during a sensor update), and a scan that waited behind a slow update is replaced by
the newer one instead of queueing. Why not rclpy's MultiThreadedExecutor: docs/node.md.
"""
from __future__ import annotations

import functools
import sys
import threading
from collections import Counter

import numpy as np
import rclpy
from geometry_msgs.msg import PoseArray, PoseWithCovarianceStamped
from nav_msgs.msg import OccupancyGrid, Odometry
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import LaserScan
from std_msgs.msg import Float32
from std_srvs.srv import Empty

from localization.core.localizer import Localizer, PoseEstimate
from localization.core.occupancy_map import MapError, OccupancyMap
from localization.core.parameters import NODE_NAME, ParameterError
from localization.ros import messages
from localization.ros.conversions import (
    pose_from_msg,
    pose_from_pose_with_covariance,
    scan_from_msg,
    twist_from_odometry,
)
from localization.ros.logging_bridge import stdlib_logger
from localization.ros.parameters import MAP_QOS, ODOM_QOS, QOS_OVERRIDES, SCAN_QOS, declare_parameters
from localization.ros.scan_worker import LatestScanWorker
from localization.ros.stamps import StampBook
from localization.ros.tf_broadcaster import TransformBroadcaster

POSE_TOPIC = "/pf/pose/odom"
PARTICLES_TOPIC = "/pf/particles"
HEALTH_TOPIC = "/pf/health"  # std_msgs/Float32: scan-map agreement of the estimate (localization.health)
TIME_JUMP = 1.0  # seconds: data stamps this far back (a bag replayed again) restart the TF stamps


def _counted(key: str):
    """Count a callback in ``node.counts[key]`` once it has finished (diagnostics; tests wait on it)."""
    def decorate(callback):
        @functools.wraps(callback)
        def counted(self, *args):
            try:
                return callback(self, *args)
            finally:
                self.counts[key] += 1
        return counted
    return decorate


class ParticleFilterNode(Node):
    def __init__(self, **node_kwargs):
        super().__init__(NODE_NAME, **node_kwargs)
        try:
            self.params = declare_parameters(self)
        except ParameterError as exc:
            self.get_logger().fatal(str(exc))
            self.destroy_node()
            raise
        p = self.params
        self.localizer = Localizer(p, stdlib_logger(self))
        self.counts = Counter()  # messages handled per input (diagnostics, tests)
        self.stamps = StampBook()
        self._odom_lock = threading.Lock()  # pairs the estimate with the odometry pose (map -> odom)
        self._odom_pose = None
        self._tf_lock = threading.Lock()
        self._last_tf_stamp = -np.inf
        self._last_data_stamp = None

        self.pose_pub = self.create_publisher(Odometry, POSE_TOPIC, 10)
        self.particles_pub = self.create_publisher(PoseArray, PARTICLES_TOPIC, 5)
        self.health_pub = self.create_publisher(Float32, HEALTH_TOPIC, 10)
        self.tf = None if p.publish_tf == "none" else TransformBroadcaster(self)
        self.scan_worker = LatestScanWorker(self.process_scan, self.get_logger().error)
        self.create_subscription(OccupancyGrid, p.map_topic, self.on_map, MAP_QOS)
        self.create_subscription(PoseWithCovarianceStamped, p.initialpose_topic, self.on_initialpose, 10)
        self.create_subscription(LaserScan, p.scan_topic, self.on_scan, SCAN_QOS,
                                 qos_overriding_options=QOS_OVERRIDES)
        self.create_subscription(Odometry, p.odom_topic, self.on_odometry, ODOM_QOS,
                                 qos_overriding_options=QOS_OVERRIDES)
        self.create_service(Empty, "~/reinitialize_global_localization", self.on_reinitialize_global)
        self.get_logger().info(
            f"particle filter ready for input: {p.num_particles} particles, map {p.map_topic}, scans "
            f"{p.scan_topic}, odometry {p.odom_topic}; publishing {POSE_TOPIC}, {PARTICLES_TOPIC}, {HEALTH_TOPIC}, "
            f"TF {p.publish_tf}")

    # ------------------------------------------------------------------ inputs
    @_counted("map")
    def on_map(self, msg: OccupancyGrid) -> None:
        try:
            occupancy_map = OccupancyMap.from_msg(msg)
        except MapError as exc:
            self.get_logger().error(f"map on {self.params.map_topic} rejected: {exc}")
            return
        if occupancy_map.frame_id != self.params.map_frame:
            self.get_logger().warning(f"map frame {occupancy_map.frame_id!r} differs from map_frame "
                                      f"{self.params.map_frame!r}; using it as {self.params.map_frame!r}")
        replacing = self.localizer.has_map
        try:
            self.localizer.set_map(occupancy_map)
        except MapError as exc:
            self.get_logger().error(f"map on {self.params.map_topic} rejected: {exc}")
            return
        self.get_logger().info(f"{'new ' if replacing else ''}map {occupancy_map.width}x{occupancy_map.height} "
                               f"cells at {occupancy_map.resolution:.4f} m")
        if self.localizer.ready and not replacing:  # global localization, or a pose that came first
            self._publish_particles(self._last_data_stamp or 0.0)

    @_counted("initialpose")
    def on_initialpose(self, msg: PoseWithCovarianceStamped) -> None:
        data = pose_from_pose_with_covariance(msg)
        if data.frame_id not in ("", self.params.map_frame):
            self.get_logger().warning(f"initial pose in frame {data.frame_id!r} ignored: it must be in the map "
                                      f"frame {self.params.map_frame!r}")
            return
        stamp = self.stamps.remember(msg.header.stamp) if data.stamp > 0 else (self._last_data_stamp or 0.0)
        if not self.localizer.set_initial_pose(data.pose, data.covariance, stamp):
            return  # not finite: the Localizer said why
        x, y, th = data.pose
        self.get_logger().info(f"initial pose ({x:.2f}, {y:.2f}, {th:.2f}): particles re-initialised")
        if self.localizer.ready:
            self._publish_particles(stamp)

    @_counted("reinitialize_global")
    def on_reinitialize_global(self, request, response):
        stamp = self._last_data_stamp or self.get_clock().now().nanoseconds * 1e-9
        if self.localizer.initialize_global(stamp):
            self.get_logger().info(f"global localization: {self.localizer.filter.num_particles} particles spread "
                                   "over the free space of the map")
            self._publish_particles(stamp)
        return response

    @_counted("odom")
    def on_odometry(self, msg: Odometry) -> None:
        twist = twist_from_odometry(msg)
        stamp = self.stamps.remember(msg.header.stamp)
        odom_pose = pose_from_msg(msg.pose.pose)
        with self._odom_lock:
            est = self.localizer.on_odometry(twist)
            self._odom_pose = odom_pose
        self._last_data_stamp = stamp
        if est is not None:  # None before a map and an initial pose (the Localizer logs that, throttled)
            self._publish_pose(PoseEstimate(stamp, est.pose, est.covariance), odom_pose)

    def on_scan(self, msg: LaserScan) -> None:
        """Subscription callback: hand the scan over to the sensor-update thread."""
        self.counts["scan_received"] += 1
        self.scan_worker.put(msg)

    @_counted("scan")
    def process_scan(self, msg: LaserScan) -> None:
        """One scan through the Localizer, then the outputs (the sensor-update thread runs this;
        tests may call it directly)."""
        stamp = self.stamps.remember(msg.header.stamp)
        est = self.localizer.on_scan(scan_from_msg(msg))
        self._last_data_stamp = stamp
        if est is not None:  # None when not ready, or no update was due
            with self._odom_lock:  # an estimate and odometry pose that belong together
                now, odom_pose = self.localizer.estimate, self._odom_pose
            # re-stamped: odometry arriving meanwhile may re-stamp the Localizer's estimate object
            self._publish_pose(PoseEstimate(stamp, est.pose, est.covariance), odom_pose, now)
            self._publish_particles(stamp)
            health = messages.health_msg(self.localizer.health)
            if health is not None:  # NaN while the cloud is still spread (global localization)
                self.health_pub.publish(health)

    def destroy_node(self):
        worker = getattr(self, "scan_worker", None)
        if worker is not None:
            worker.stop()  # no sensor update publishes through a destroyed node
            self.get_logger().info(f"scans: {self.counts['scan_received']} received, {self.counts['scan']} "
                                   f"processed, {worker.dropped} replaced by a newer one while waiting")
        return super().destroy_node()

    # ------------------------------------------------------------------ outputs
    def _publish_pose(self, est, odom_pose, est_with_odom=None) -> None:
        p, stamp = self.params, self.stamps.lookup(est.stamp)
        msg = messages.odometry_msg(est.pose, est.covariance, stamp, p.map_frame, p.particle_filter_frame)
        if msg is None:
            self.get_logger().warning("non-finite estimate not published", throttle_duration_sec=5.0)
            return
        self.pose_pub.publish(msg)
        if self.tf is None:
            return
        if p.publish_tf == "map_to_odom":
            if odom_pose is None:
                return
            pose = messages.map_to_odom((est_with_odom or est).pose, odom_pose)
            tf = messages.transform_msg(pose, stamp, p.map_frame, p.odom_frame)
        else:
            tf = messages.transform_msg(est.pose, stamp, p.map_frame, p.particle_filter_frame)
        with self._tf_lock:  # TF stamps only move forward (no TF_REPEATED_DATA), unless time jumps back
            if tf is None or self._last_tf_stamp - TIME_JUMP < est.stamp <= self._last_tf_stamp:
                return
            self._last_tf_stamp = est.stamp
            self.tf.send([tf])

    def _publish_particles(self, stamp: float) -> None:
        if self.params.max_particles_published > 0:
            self.particles_pub.publish(messages.pose_array_cdr(
                self.localizer.filter.particles, self.stamps.lookup(stamp), self.params.map_frame,
                self.params.max_particles_published))


def main(args=None) -> int:
    rclpy.init(args=args)
    try:
        node = ParticleFilterNode()
    except ParameterError:
        rclpy.try_shutdown()
        return 1
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
