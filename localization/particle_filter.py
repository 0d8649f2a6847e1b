"""The ``particle_filter`` ROS 2 node: wiring only (ROS messages -> converters -> Localizer ->
message builders -> ROS messages). See docs/node.md for topics, frames and parameters.

    ros2 run localization particle_filter --ros-args --params-file config/params.yaml
    python -m localization.particle_filter --ros-args -p num_particles:=500

Threading: a SingleThreadedExecutor runs every subscription callback (each takes well under a
millisecond or two); the scan callback only leaves the message in a one-slot mailbox for the
sensor-update thread (``LatestScanWorker``), which runs the sensor update (the
compiled kernels release the GIL) and publishes its outputs. So a slow sensor update never delays
the pose published on odometry (the Localizer queues odometry that arrives during a sensor
update), and a scan that waited behind a slow update is replaced by the newer one instead of
queueing. (rclpy's MultiThreadedExecutor, measured at 4000 particles on the real bags at 40 Hz:
odometry-to-pose latency 0.7-0.9 s from executor overhead and GIL contention; this design: ~4 ms.)
"""
from __future__ import annotations

import functools
import logging
import sys
import threading
from collections import Counter

import numpy as np
import rclpy
from geometry_msgs.msg import PoseArray, PoseWithCovarianceStamped
from nav_msgs.msg import OccupancyGrid, Odometry
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.exceptions import InvalidParameterTypeException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import LaserScan
from std_msgs.msg import Float32
from std_srvs.srv import Empty

from . import messages
from .conversions import pose_from_msg, pose_from_pose_with_covariance, scan_from_msg, twist_from_odometry
from .localizer import Localizer, PoseEstimate
from .occupancy_map import MapError, OccupancyMap
from .parameters import BY_NAME, NODE_NAME, PARAMETERS, ParameterError, Parameters
from .tf_broadcaster import TransformBroadcaster

POSE_TOPIC = "/pf/pose/odom"
PARTICLES_TOPIC = "/pf/particles"
HEALTH_TOPIC = "/pf/health"  # std_msgs/Float32: scan-map agreement of the estimate (localization.health)
MAP_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
ODOM_QOS = QoSProfile(depth=50, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)
# scan and odometry QoS can be changed with the standard parameters, e.g.
# qos_overrides./scan.subscription.reliability:=reliable
QOS_OVERRIDES = QoSOverridingOptions.with_default_policies()
# sensor-data QoS (best effort, depth 5: the callback only hands the scan to the sensor-update
# thread, whose one-slot mailbox keeps the newest, so a scan waiting behind a slow update never
# queues). Depth 1 lost ~35 % of 40 Hz scans whenever the callback thread was briefly busy.
SCAN_QOS = QoSProfile(depth=5, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.VOLATILE)
TIME_JUMP = 1.0  # seconds: data stamps this far back (a bag replayed again) restart the TF stamps
_TYPE_NAMES = {bool: "a boolean (true/false)", int: "an integer", float: "a float", str: "a string"}


def declare_parameters(node: Node) -> Parameters:
    """Declare every parameter of ``localization.parameters`` (read-only, with its description)
    and return the validated values; raises ParameterError with every problem found."""
    overrides = getattr(node, "_parameter_overrides", {}) or {}
    values, problems = {}, []
    for p in PARAMETERS:
        desc = ParameterDescriptor(description=f"{p.description} [{p.rule}]" if p.rule else p.description,
                                   read_only=True)
        try:
            values[p.name] = node.declare_parameter(p.name, p.default, desc).value
        except InvalidParameterTypeException:
            given = overrides[p.name].value if p.name in overrides else None
            if isinstance(p.default, float) and isinstance(given, int) and not isinstance(given, bool):
                values[p.name] = node.declare_parameter(p.name, float(given), desc, ignore_override=True).value
            else:
                problems.append(f"{p.name}={given!r} must be {_TYPE_NAMES[type(p.default)]}"
                                + (f" ({p.rule})" if p.rule else ""))
    unknown = sorted(n for n in overrides if n not in BY_NAME and n != "use_sim_time"
                     and not n.startswith("qos_overrides."))
    if unknown:
        node.get_logger().warning(f"unknown parameters ignored: {', '.join(unknown)}")
    try:
        params = Parameters(values)
    except ParameterError as exc:
        problems.append(str(exc).removeprefix("invalid parameters: "))
    if problems:
        raise ParameterError("invalid parameters: " + "; ".join(problems))
    return params


class _RclpyHandler(logging.Handler):
    """Forwards standard-library log records (the ROS-free core logs that way) to a ROS logger."""

    def __init__(self, ros_logger):
        super().__init__()
        self.ros_logger = ros_logger

    def emit(self, record: logging.LogRecord) -> None:
        try:
            message, level = self.format(record), record.levelno
            if level >= logging.ERROR:
                self.ros_logger.error(message)
            elif level >= logging.WARNING:
                self.ros_logger.warning(message)
            elif level >= logging.INFO:
                self.ros_logger.info(message)
            else:
                self.ros_logger.debug(message)
        except Exception:  # noqa: BLE001 - logging must never break a callback
            self.handleError(record)


def stdlib_logger(node: Node) -> logging.Logger:
    """A ``logging.Logger`` (own instance, not in the global registry) writing to the node's logger."""
    logger = logging.Logger(f"localization.{node.get_name()}")
    logger.addHandler(_RclpyHandler(node.get_logger()))
    logger.setLevel(logging.DEBUG if node.get_logger().is_enabled_for(rclpy.logging.LoggingSeverity.DEBUG)
                    else logging.INFO)
    return logger


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


class LatestScanWorker:
    """A thread that handles the newest scan left by ``put``: a one-slot mailbox, so a scan that
    arrives while the previous one is still being processed replaces any scan still waiting
    (``dropped`` counts those) instead of queueing behind it."""

    def __init__(self, handle, log_error, name: str = "sensor_update"):
        self._handle, self._log_error = handle, log_error
        self._cond = threading.Condition()
        self._pending = None
        self._stop = False
        self.dropped = 0
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def put(self, item) -> None:
        with self._cond:
            if self._pending is not None:
                self.dropped += 1
            self._pending = item
            self._cond.notify()

    def _run(self) -> None:
        while True:
            with self._cond:
                while self._pending is None and not self._stop:
                    self._cond.wait()
                if self._stop:
                    return
                item, self._pending = self._pending, None
            try:
                self._handle(item)
            except Exception as exc:  # noqa: BLE001 - a bad scan must never kill the thread
                self._log_error(f"sensor update failed: {exc!r}")

    def stop(self, timeout: float = 5.0) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify()
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout)


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
        self.stamps = messages.StampBook()
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
            f"{p.scan_topic}, odometry {p.odom_topic}; publishing {POSE_TOPIC}, {PARTICLES_TOPIC}, {HEALTH_TOPIC}, TF {p.publish_tf}")

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
            est = self.localizer.on_odometry(stamp, twist.vx, twist.vy, twist.wz)
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
        s = scan_from_msg(msg)
        est = self.localizer.on_scan(stamp, s.ranges, s.angle_min, s.angle_max, s.angle_increment,
                                     s.range_min, s.range_max)
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
