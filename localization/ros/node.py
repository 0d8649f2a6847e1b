"""The ``particle_filter`` ROS 2 node: wiring only (ROS messages -> converters -> Localizer ->
message builders -> ROS messages). See docs/node.md for topics, frames and parameters.

    ros2 run localization particle_filter --ros-args --params-file config/real_params.yaml
    python -m localization.particle_filter --ros-args -p num_particles:=500
    particle_filter --help

``LocalizationMixin.__init__`` creates every field and declares the parameters; the wiring comes in
the four steps of a lifecycle node: ``_configure`` (localizer, publishers, services, worker
threads), ``_activate`` (subscriptions, timers), ``_deactivate``, ``_cleanup``.
``ParticleFilterNode`` runs the first two at construction; ``localization.ros.lifecycle_node``
maps them onto configure/activate/deactivate/cleanup. Each callback converts its message, makes one
call into the core and publishes. The parts with a job of their own:

    map_install         a map checked, prepared (off-thread when the sensor model says it is slow), installed
    outputs             publishers; one publish rule per stream (core.publish_rule)
    laser_tf            the laser pose from TF, else the laser_offset_* parameters
    latency             each scan's way through the node, for /diagnostics
    diagnostics         /diagnostics and the log lines of its problems
    pose_persistence    the start pose (parameters or persisted) and the persisted estimate
    runtime_parameters  parameters set while the node runs: checked, prepared, applied between updates
    cli                 the command line, spin, SIGINT/SIGTERM

Threading: one executor thread runs every callback (``cli.make_executor``). With ``sensor_update_thread``
the scan callback only queues the message for a sensor-update thread (``scan_worker``), which runs the
sensor update and publishes the corrections, so the odometry callbacks never wait behind an update: the
localizer carries each odometry pose under the timeline's own short lock while the update holds its
lock. Scans that wait in the localizer for the odometry that reaches their time are run on that thread
as soon as the odometry does (``poke``). Without it (the default: a seeded node is reproducible bit for
bit) the scan callback runs the sensor update (as
nav2_amcl's laser callback does), or the odometry callback that reaches a newer scan's time does, and
odometry waits in its queue meanwhile (why not rclpy's MultiThreadedExecutor, and the measured costs:
docs/node.md). Every output is stamped with the time it describes, on the scan clock (``outputs``,
docs/node.md).
"""
from __future__ import annotations

import functools
import math
import sys
import time
from collections import Counter

from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import OccupancyGrid, Odometry
from rclpy.node import Node
from sensor_msgs.msg import LaserScan
from std_srvs.srv import Empty

from localization.core.localizer import Ignored, Localizer
from localization.core.parameters import NODE_NAME, ParameterError
from localization.core.watchdog import Watchdog
from localization.ros.cdr import CdrError, read_odometry, read_scan
from localization.ros.cli import spin_node
from localization.ros.conversions import odometry_from_msg, pose_from_pose_with_covariance, scan_from_msg
from localization.ros.diagnostics import Diagnostics
from localization.ros.laser_tf import LaserPoseSource
from localization.ros.latency import LatencyBook
from localization.ros.live_view import start_live_view
from localization.ros.logging_bridge import stdlib_logger
from localization.ros.map_install import MapInstaller
from localization.ros.outputs import DIAGNOSTICS_TOPIC, HEALTH_TOPIC, ODOM_POSE_TOPIC, PARTICLES_TOPIC, Outputs
from localization.ros.parameters import MAP_QOS, ODOM_QOS, QOS_OVERRIDES, SCAN_QOS, declare_parameters
from localization.ros.pose_persistence import PosePersistence, initial_pose_at_start
from localization.ros.runtime_parameters import RuntimeParameters
from localization.ros.scan_worker import ScanQueueWorker
from localization.ros.stamps import StampBook


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


class LocalizationMixin:
    """The node's wiring, for ``rclpy.node.Node`` and ``rclpy.lifecycle.LifecycleNode`` alike."""

    def __init__(self, **node_kwargs):
        super().__init__(NODE_NAME, **node_kwargs)
        self.params = None  # core.parameters.Parameters, validated (declare_parameters)
        self.counts = Counter()  # messages handled per input (diagnostics, tests)
        self.stamps = StampBook()  # exact input stamps, for the outputs
        self.latency = LatencyBook()
        self.localizer: Localizer | None = None  # the rest exists while configured
        self.watchdog: Watchdog | None = None
        self.outputs: Outputs | None = None
        self.diagnostics: Diagnostics | None = None
        self.laser: LaserPoseSource | None = None
        self.persistence: PosePersistence | None = None
        self.map_install: MapInstaller | None = None
        self.scan_worker: ScanQueueWorker | None = None  # sensor_update_thread
        self.live_view = None  # ros.live_view.LiveView (foxglove_port)
        self._pf_subs, self._pf_timers, self._pf_services = [], [], []
        self._configured = False
        self._last_odom = None  # (t'_k, its odometry pose or None) of the newest odometry message
        self._last_data_stamp = None  # s, scan clock: the newest input's time
        self.runtime: RuntimeParameters | None = None  # parameters set while the node runs
        try:
            self.params = declare_parameters(self)
        except ParameterError as exc:
            self.get_logger().fatal(str(exc))
            self.destroy_node()
            raise
        self.runtime = RuntimeParameters(self)

    # ------------------------------------------------------------------ lifecycle steps
    def _configure(self) -> None:
        p, log = self.params, self.get_logger()
        self.counts.clear()  # a new run: the statistics start again
        self.latency.clear()
        self._last_odom = self._last_data_stamp = None
        self.localizer = Localizer(p, stdlib_logger(self))
        self.watchdog = Watchdog(time.monotonic(), odom_timeout=p.odom_timeout, scan_timeout=p.scan_timeout,
                                 map_timeout=p.map_timeout, tf_timeout=p.tf_timeout, scan_topic=p.scan_topic,
                                 odom_topic=p.odom_topic, map_topic=p.map_topic, health_lost_floor=p.health_lost_floor)
        self.outputs = Outputs(self, p, self.localizer, self.stamps, self.watchdog, self.latency)
        self.diagnostics = Diagnostics(self, p, self.watchdog)
        self.laser = LaserPoseSource(self, p, self.localizer, self.watchdog)
        self.persistence = PosePersistence(p, log)
        if p.sensor_update_thread:
            self.scan_worker = ScanQueueWorker(self.process_scan, log.error, on_poke=self.run_released_scans)
        self.map_install = MapInstaller(p, self.localizer, self.watchdog, log, self.counts, self._on_map_installed)
        self._pf_services = [
            self.create_service(Empty, "~/reinitialize_global_localization", self.on_reinitialize_global),
            self.create_service(Empty, "request_nomotion_update", self.on_request_nomotion_update),
        ]
        self.live_view = start_live_view(p, log)  # foxglove_port >= 0
        initial_pose_at_start(p, self.localizer, log)
        self._configured = True

    def _activate(self) -> None:
        p = self.params
        self._pf_subs = [
            self.create_subscription(OccupancyGrid, p.map_topic, self.on_map, MAP_QOS),
            self.create_subscription(PoseWithCovarianceStamped, p.initialpose_topic, self.on_initialpose, 10),
            # raw: the CDR bytes are read by ros.cdr (no Python message built), a scan's on the
            # sensor-update thread when there is one
            self.create_subscription(LaserScan, p.scan_topic, self.on_scan, SCAN_QOS,
                                     qos_overriding_options=QOS_OVERRIDES, raw=True),
            self.create_subscription(Odometry, p.odom_topic, self.on_odometry, ODOM_QOS,
                                     qos_overriding_options=QOS_OVERRIDES, raw=True),
        ]
        self.laser.listen()
        self._pf_timers = [self.create_timer(p.diagnostics_period, self.publish_diagnostics)]
        if p.persist_pose:
            self._pf_timers.append(self.create_timer(p.persist_pose_period, self.persist_pose))
        self.watchdog.start = time.monotonic()
        self.get_logger().info(
            f"particle filter ready for input: {p.num_particles} particles, map {p.map_topic}, scans "
            f"{p.scan_topic}, odometry {p.odom_topic}; publishing {p.pose_topic}, {ODOM_POSE_TOPIC}, "
            f"{PARTICLES_TOPIC}, {HEALTH_TOPIC}, {DIAGNOSTICS_TOPIC}, TF {p.publish_tf}")

    def _deactivate(self) -> None:
        for sub in self._pf_subs:
            self.destroy_subscription(sub)
        for timer in self._pf_timers:
            self.destroy_timer(timer)
        self._pf_subs, self._pf_timers = [], []
        if self.laser is not None:
            self.laser.close()

    def _cleanup(self) -> None:
        for worker in (self.map_install, self.scan_worker):
            if worker is not None:
                worker.stop()  # no sensor update publishes through a destroyed node
        if self.live_view is not None:
            self.live_view.close()
        if self._configured:
            self.get_logger().info(self.diagnostics.run_summary(self.scan_worker))
            if self.params.persist_pose:
                self.persist_pose()
            self.outputs.destroy()
            for srv in self._pf_services:
                self.destroy_service(srv)
        self._pf_services = []
        self.live_view = self.scan_worker = self.map_install = None
        self._configured = False

    def _shutdown_wiring(self) -> None:
        """Deactivate (if active: subscriptions exist) and clean up (if configured); safe to repeat."""
        if self._pf_subs:
            self._deactivate()
        if self._configured:
            self._cleanup()
        if self.runtime is not None:
            self.runtime.stop()

    # ------------------------------------------------------------------ inputs
    def on_map(self, msg: OccupancyGrid) -> None:
        self.map_install.receive(msg)

    def _on_map_installed(self, occupancy_map, replacing: bool) -> None:
        """The first pose as soon as the map is usable, at the newest odometry's time."""
        if self.live_view is not None:
            self.live_view.set_map(occupancy_map)
        if not self.localizer.ready:
            return
        last_odom = self._last_odom
        if last_odom is not None and not replacing:
            est = self.localizer.estimate_at(last_odom[0])
            if est is not None:
                self.outputs.publish_odom_pose(est, last_odom[1])
        self.outputs.publish_particles(self._last_data_stamp or 0.0)

    @_counted("initialpose")
    def on_initialpose(self, msg: PoseWithCovarianceStamped) -> None:
        data = pose_from_pose_with_covariance(msg)
        if data.frame_id not in ("", self.params.map_frame):
            self.get_logger().warning(f"initial pose in frame {data.frame_id!r} ignored: it must be in the map "
                                      f"frame {self.params.map_frame!r}")
            return
        stamp = self.stamps.remember(msg.header.stamp) if data.stamp > 0 else (self._last_data_stamp or 0.0)
        if not self.localizer.set_initial_pose(data.pose, data.covariance, stamp) or not self.localizer.ready:
            return  # refused, or kept until a map arrives: the Localizer said so
        x, y, th = data.pose
        self.get_logger().info(f"initial pose ({x:.2f}, {y:.2f}, {th:.2f}): particles re-initialised")
        self.outputs.publish_particles(stamp)

    @_counted("reinitialize_global")
    def on_reinitialize_global(self, request, response):
        stamp = self._last_data_stamp or self.get_clock().now().nanoseconds * 1e-9
        if self.localizer.initialize_global(stamp):
            self.get_logger().info(f"global localization: {self.localizer.num_particles} particles spread "
                                   "over the free space of the map")
            self.outputs.publish_particles(stamp)
        return response

    @_counted("nomotion_update")
    def on_request_nomotion_update(self, request, response):
        """nav2_amcl's service: the next scan updates the filter although the car has not moved."""
        self.localizer.request_update()
        self.get_logger().info("no-motion update requested: the next scan updates the filter")
        return response

    @_counted("odom")
    def on_odometry(self, msg) -> None:
        """The pose carried forward to this message's time t'_k on /pf/pose/odom and TF (map -> odom
        pairs it with this message's own odometry pose), then any corrections the odometry released
        (scans wait in the localizer for the odometry that reaches their time). Odometry that
        arrives before the localizer is ready (no map yet, range table being built, no initial
        pose) is kept in its history all the same. ``msg``: the CDR bytes, or a nav_msgs/Odometry."""
        self.watchdog.odom_received(time.monotonic())
        if self.localizer.map_pending and not self.localizer.has_map:
            self.watchdog.odom_waiting_for_table += 1
        try:
            odom = odometry_from_msg(msg) if isinstance(msg, Odometry) else read_odometry(msg)
        except CdrError as exc:
            self.get_logger().warning(f"odometry message on {self.params.odom_topic} ignored: {exc}",
                                      throttle_duration_sec=5.0)
            return
        t_odom = self.stamps.remember(odom.stamp) + self.params.odom_time_offset  # scan clock
        odom_pose = odom.pose if self.outputs.map_to_odom else None
        # with the sensor-update thread, scans this odometry releases run there (at its next scan), not here
        est = self.localizer.on_odometry(odom.twist, run_scans=self.scan_worker is None)
        if math.isfinite(t_odom):
            self._last_data_stamp = t_odom
            self._last_odom = (t_odom, odom_pose)
        if est is not None:  # None before a map and an initial pose (the Localizer logs that, throttled)
            self.outputs.publish_odom_pose(est, odom_pose)
        if self.scan_worker is None:  # with the sensor-update thread, that thread publishes the corrections
            self.outputs.publish_corrections()
        elif self.localizer.scans_due:  # a scan waited for this odometry: the thread runs it now
            self.scan_worker.poke()

    def on_scan(self, msg) -> None:
        """Subscription callback: the scan (serialized bytes, or a message) through the sensor update
        here, or handed over to the sensor-update thread (``sensor_update_thread``)."""
        now = time.monotonic()
        self.watchdog.scan_received(now)
        if self.scan_worker is None:
            self.process_scan(msg, now)
        else:
            self.scan_worker.put(msg)

    @_counted("scan")
    def process_scan(self, msg, t_put: float | None = None) -> None:
        """One scan (a LaserScan, or its CDR bytes) through the Localizer, then the outputs (the
        sensor-update thread runs this; tests may call it directly). Times each part for /diagnostics."""
        t_start = time.monotonic()
        t_put = t_start if t_put is None else t_put
        if isinstance(msg, LaserScan):
            stamp, scan = msg.header.stamp, scan_from_msg(msg)
        else:
            try:
                stamp, scan = read_scan(msg)
            except CdrError as exc:
                self.get_logger().warning(f"scan message on {self.params.scan_topic} ignored: {exc}",
                                          throttle_duration_sec=5.0)
                return
        t_deser = time.monotonic()
        self.stamps.remember(stamp)
        if self.laser.pending:
            self.laser.resolve(scan.frame_id, t_start)
        t_conv = time.monotonic()
        t_s = self.localizer.scan_time(scan)
        if self.localizer.ready and math.isfinite(t_s):  # the scan's way so far, until its correction
            self.latency.scan_converted(t_s, t_put, t_start, t_deser, t_conv)
        ignored = self.localizer.on_scan(scan).ignored  # not ready: it says why (throttled)
        if ignored in (Ignored.MAP_PENDING, Ignored.NOT_READY):  # no map, range table being built, no initial pose
            building = ignored is Ignored.MAP_PENDING
            self.watchdog.scans_waiting_for_table += int(building)
            self.watchdog.scans_not_used(t_conv, 1, "while the range table was prepared" if building
                                         else f"while waiting for {self.diagnostics.waiting_for(self.localizer)}")
        if self.live_view is not None:
            self.live_view(scan, self.localizer)
        if math.isfinite(scan.stamp):
            self._last_data_stamp = scan.stamp
        self.outputs.publish_corrections()
        self.watchdog.scan_processed(time.monotonic())

    def run_released_scans(self) -> None:
        """The sensor-update thread: the scans the odometry has released since the last scan, and their
        corrections published."""
        self.localizer.run_waiting()
        self.outputs.publish_corrections()

    # ------------------------------------------------------------------ timers
    def diagnostic_status(self):
        status = self.diagnostics.status(self.localizer, self.laser.describe(), self.scan_worker)
        status.values["parameters changed"] = self.runtime.last
        return status

    def publish_diagnostics(self) -> None:
        self.laser.tidy()  # the executor's thread: subscriptions the sensor-update thread ended
        self.diagnostics.publish(self.diagnostic_status(), self.outputs.publish_diagnostics)

    def persist_pose(self) -> None:
        self.persistence.save(self.localizer)


class ParticleFilterNode(LocalizationMixin, Node):
    """The plain node: configured and active from construction."""

    def __init__(self, **node_kwargs):
        super().__init__(**node_kwargs)
        self._configure()
        self._activate()

    def destroy_node(self):
        self._shutdown_wiring()
        return super().destroy_node()


def main(args=None) -> int:
    return spin_node(ParticleFilterNode, args)


if __name__ == "__main__":
    sys.exit(main())
