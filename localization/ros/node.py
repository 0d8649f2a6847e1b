"""The ``particle_filter`` ROS 2 node: wiring only (ROS messages -> converters -> Localizer ->
message builders -> ROS messages). See docs/node.md for topics, frames and parameters.

    ros2 run localization particle_filter --ros-args --params-file config/real_params.yaml
    python -m localization.particle_filter --ros-args -p num_particles:=500
    particle_filter --help

``LocalizationMixin`` holds the wiring, in the four steps of a lifecycle node: ``_configure``
(localizer, publishers, services, worker threads), ``_activate`` (subscriptions, timers),
``_deactivate``, ``_cleanup``. ``ParticleFilterNode`` runs them all at construction;
``localization.ros.lifecycle_node`` maps them onto configure/activate/deactivate/cleanup.

Threading: a SingleThreadedExecutor runs every subscription callback. The scan callback runs the
sensor update and publishes its outputs (as nav2_amcl's laser callback does) — or, when the scan is
newer than the odometry, the odometry callback that reaches its time does (the localizer keeps the
scan until then); scans arriving meanwhile wait in the subscription's queue (SCAN_QOS depth),
odometry in its own. With ``sensor_update_thread`` the scan callback only queues the message for a
sensor-update thread (``scan_worker.ScanQueueWorker``: a short FIFO) which also publishes the
corrections, so odometry poses keep flowing during an update, at the price of a GIL hand-over per
scan (measured in docs/node.md). A map whose lookup-table
ray caster needs a range table (built, or loaded from the disk cache) is prepared on a third
thread; meanwhile odometry goes into the localizer's history (the particles move through it once
the table is ready), scans cannot be used and are reported as dropped, and the first pose goes
out as soon as the table is ready. Why not rclpy's MultiThreadedExecutor: docs/node.md.

Stamps (every output is stamped with the time it describes, on the scan clock; docs/node.md):

    /pf/pose/odom, TF   x̂ ⊕ Δ(t_a, t'_k) at t'_k = t_k + odom_time_offset, on each odometry message k
    /pf/pose            x̂(t_s) at the scan's time t_s, each sensor-corrected estimate once
    /pf/particles       the cloud at the time of the newest correction published with it

Each stream only moves forward: an output older than (or as old as) the last one on its stream is
not published, unless it is more than TIME_JUMP older (a bag played again: the stream restarts).

Watchdogs: ``core.watchdog.Watchdog`` records every input; a timer publishes its status on
/diagnostics and logs each problem (no odometry while scans arrive, no scans, no map, TF, scans not
used, lost: health below health_lost_floor) when it appears and every 5 s while it lasts.

Command line (``prepare_args``): arguments outside ``--ros-args`` are an error; every
``--params-file`` must exist (a bare name is looked up in the package's config/) and have a
section for this node; unknown parameters are an error (``ros.parameters``). SIGINT and SIGTERM
end ``spin_node`` within SPIN_WAKE_S in every lifecycle state, with exit code 0.
"""
from __future__ import annotations

import functools
import math
import os
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray, PoseWithCovarianceStamped
from nav_msgs.msg import OccupancyGrid, Odometry
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import LaserScan
from std_msgs.msg import Float32
from std_srvs.srv import Empty

from localization.core import pose_store
from localization.core.localizer import Localizer, PoseEstimate
from localization.core.occupancy_map import MapError, OccupancyMap
from localization.core.parameters import NODE_NAME, PARAMETERS, ParameterError
from localization.core.recovery import TRACKING
from localization.core.watchdog import LEVEL_NAMES, ProblemLog, Watchdog
from localization.ros import messages
from localization.ros.conversions import (
    pose_from_msg,
    pose_from_pose_with_covariance,
    scan_from_msg,
    twist_from_odometry,
)
from localization.ros.logging_bridge import stdlib_logger
from localization.ros.parameters import MAP_QOS, ODOM_QOS, QOS_OVERRIDES, SCAN_QOS, declare_parameters
from localization.ros.scan_worker import ScanQueueWorker
from localization.ros.stamps import StampBook
from localization.ros.tf_broadcaster import TransformBroadcaster

ODOM_POSE_TOPIC = "/pf/pose/odom"  # nav_msgs/Odometry (the course's output)
PARTICLES_TOPIC = "/pf/particles"
HEALTH_TOPIC = "/pf/health"  # std_msgs/Float32: scan-map agreement of the estimate (localization.health)
DIAGNOSTICS_TOPIC = "/diagnostics"
TIME_JUMP = 1.0  # seconds: data stamps this far back (a bag replayed again) restart the TF stamps
TABLE_KINDS = ("lookup_table", "lookup_table_exact")  # ray casters whose map set-up builds a range table
# seconds per (free cell x heading) ray of a range-table build, per core (the estimate in the log line)
GIL_SWITCH_INTERVAL_S = 0.0005  # see spin_node
SPIN_WAKE_S = 0.2  # s: the executor's longest wait, so SIGINT/SIGTERM are acted on within it
SCAN_TIMES_KEPT = 64  # scans whose way through the node is remembered until their correction (latency)
ODOMETRY_TYPE, SCAN_TYPE = "nav_msgs/msg/Odometry", "sensor_msgs/msg/LaserScan"


def _subscribed(publisher) -> bool:
    """Whether anyone listens (True for stand-ins without the count, e.g. test recorders)."""
    count = getattr(publisher, "get_subscription_count", None)
    return count is None or count() > 0


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

    # ------------------------------------------------------------------ set-up steps
    def _shutdown_wiring(self) -> None:
        """Deactivate (if active: subscriptions exist) and clean up (if configured); safe to repeat."""
        if getattr(self, "_pf_subs", None):
            self._deactivate()
        if getattr(self, "_configured", False):
            self._cleanup()

    def _declare_or_destroy(self) -> None:
        """``_declare``; on a bad parameter the half-made node is destroyed and the error re-raised."""
        try:
            self._declare()
        except ParameterError:
            self.destroy_node()
            raise

    def _declare(self) -> None:
        try:
            self.params = declare_parameters(self)
        except ParameterError as exc:
            self.get_logger().fatal(str(exc))
            raise
        self.counts = Counter()  # messages handled per input (diagnostics, tests)
        self.localizer = None
        self.live_view = None
        self.watchdog = None
        self.scan_worker = self.map_worker = None
        self._pf_subs, self._pf_timers = [], []
        self._configured = False

    def _configure(self) -> None:
        p = self.params
        self.localizer = Localizer(p, stdlib_logger(self))
        self.stamps = StampBook()
        self.counts = Counter()  # a new run: the statistics start again
        self.watchdog = Watchdog(time.monotonic(), odom_timeout=p.odom_timeout, scan_timeout=p.scan_timeout,
                                 map_timeout=p.map_timeout, tf_timeout=p.tf_timeout, scan_topic=p.scan_topic,
                                 odom_topic=p.odom_topic, map_topic=p.map_topic, health_lost_floor=p.health_lost_floor)
        self.problem_log = ProblemLog()
        self._odom_out_lock = threading.Lock()  # /pf/pose/odom and TF: one stamp order
        self._last_odom_out = -np.inf  # s, scan clock: the newest stamp on /pf/pose/odom and TF
        self._pose_out_lock = threading.Lock()  # /pf/pose, /pf/particles, /pf/health
        self._last_pose_out = -np.inf  # s, scan clock: the newest stamp on /pf/pose
        self._scan_times: dict[float, tuple] = {}  # scan time t_s -> (monotonic times of its way), for latency
        self._worker_dropped = 0  # scans the sensor-update queue dropped, already reported
        self._last_odom = None  # (t'_k, its odometry pose or None) of the newest odometry message
        self._last_data_stamp = None  # s, scan clock: the newest input's time
        self._map_generation = 0
        self._laser_source = None  # "tf" | "parameters" once decided
        self._laser_lookup = None
        self._last_persisted = None

        self.pose_pub = self.create_publisher(Odometry, ODOM_POSE_TOPIC, 10)
        self.pose_cov_pub = self.create_publisher(PoseWithCovarianceStamped, p.pose_topic, 10)
        self.particles_pub = self.create_publisher(PoseArray, PARTICLES_TOPIC, 5)
        self.health_pub = self.create_publisher(Float32, HEALTH_TOPIC, 10)
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, 10)
        self.tf = None if p.publish_tf == "none" else TransformBroadcaster(self)
        self._map_to_odom = p.publish_tf == "map_to_odom"  # only then is the odometry pose needed
        if p.sensor_update_thread:
            self.scan_worker = ScanQueueWorker(self.process_scan, self.get_logger().error)
        self.map_worker = ScanQueueWorker(self._install_map, self.get_logger().error, name="map_preparation",
                                          depth=1)
        self._pf_services = [
            self.create_service(Empty, "~/reinitialize_global_localization", self.on_reinitialize_global),
            self.create_service(Empty, "request_nomotion_update", self.on_request_nomotion_update),
        ]
        self.live_view = self._start_live_view()
        self._initial_pose_at_start()
        self._configured = True

    def _start_live_view(self):
        """The Foxglove live view when foxglove_port >= 0 (a browser-only way to watch the filter)."""
        p = self.params
        if p.foxglove_port < 0:
            return None
        from localization.ros.live_view import LiveView, LiveViewError
        try:
            view = LiveView(port=p.foxglove_port, host=p.foxglove_host, map_frame=p.map_frame,
                            base_frame=p.particle_filter_frame)
        except LiveViewError as exc:
            self.get_logger().error(f"live view not started: {exc}")
            return None
        self.get_logger().info(f"live view: Foxglove WebSocket on ws://{view.host}:{view.port}")
        return view

    def _activate(self) -> None:
        p = self.params
        self._pf_subs = [
            self.create_subscription(OccupancyGrid, p.map_topic, self.on_map, MAP_QOS),
            self.create_subscription(PoseWithCovarianceStamped, p.initialpose_topic, self.on_initialpose, 10),
            # raw: the CDR bytes are deserialized on the sensor-update thread, not the executor's
            self.create_subscription(LaserScan, p.scan_topic, self.on_scan, SCAN_QOS,
                                     qos_overriding_options=QOS_OVERRIDES, raw=True),
            self.create_subscription(Odometry, p.odom_topic, self.on_odometry, ODOM_QOS,
                                     qos_overriding_options=QOS_OVERRIDES),
        ]
        if p.laser_pose_from_tf and self._laser_source != "tf":
            try:
                from localization.ros.laser_tf import LaserPoseLookup
                own = p.odom_frame if p.publish_tf == "map_to_odom" else p.particle_filter_frame
                self._laser_lookup = LaserPoseLookup(self, ignore_children={own})
            except ImportError as exc:
                self.get_logger().warning(f"laser pose: TF not available ({exc}); using laser_offset_* parameters")
                self._laser_source = "parameters"
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
        if self._laser_lookup is not None:
            self._laser_lookup.close()
            self._laser_lookup = None

    def _cleanup(self) -> None:
        for worker in (self.map_worker, self.scan_worker):
            if worker is not None:
                worker.stop()  # no sensor update publishes through a destroyed node
        if getattr(self, "live_view", None) is not None:
            self.live_view.close()
            self.live_view = None
        if self._configured:
            self._report_worker_drops()
            w = self.watchdog
            self.get_logger().info(
                f"scans: {w.scans_received} received, {w.scans_processed} processed, {w.scans_dropped} not used "
                f"({w.scans_waiting_for_table} while the range table was prepared); {w.sensor_updates} sensor "
                f"updates; odometry: {w.odom_count} received ({w.odom_waiting_for_table} while the range table was "
                f"prepared, kept); scan -> pose: {w.run_summary()}")
        if self.localizer is not None and self.params.persist_pose:
            self.persist_pose()
        if not self._configured:
            return
        from rclpy.publisher import Publisher
        for pub in (self.pose_pub, self.pose_cov_pub, self.particles_pub, self.health_pub, self.diagnostics_pub):
            if isinstance(pub, Publisher):  # tests may have swapped in recorders
                self.destroy_publisher(pub)
        if isinstance(self.tf, TransformBroadcaster):
            self.tf.destroy()
        for srv in self._pf_services:
            self.destroy_service(srv)
        self.scan_worker = self.map_worker = None
        self._configured = False

    def _initial_pose_at_start(self) -> None:
        """nav2-style ``set_initial_pose`` + ``initial_pose.*``, else the persisted pose (opt-in)."""
        p = self.params
        if p.set_initial_pose:
            pose = np.array([p["initial_pose.x"], p["initial_pose.y"], p["initial_pose.yaw"]])
            if self.localizer.set_initial_pose(pose, None, 0.0):
                self.get_logger().info(f"initial pose from parameters ({pose[0]:.2f}, {pose[1]:.2f}, "
                                       f"{pose[2]:.2f}): localizing once a map arrives")
            return
        if not p.persist_pose or p.global_localization:
            return
        path = pose_store.pose_file(p.persist_pose_file)
        stored, why = pose_store.load_pose(path)
        if stored is None:
            self.get_logger().info(f"{why}: waiting for an initial pose")
            return
        if stored.frame_id not in ("", p.map_frame):
            self.get_logger().warning(f"persisted pose {path} is in frame {stored.frame_id!r}, not "
                                      f"{p.map_frame!r}: ignored")
            return
        if self.localizer.set_initial_pose(stored.pose, stored.covariance, 0.0):
            x, y, th = stored.pose
            self.get_logger().info(f"initial pose from the persisted pose {path} ({x:.2f}, {y:.2f}, {th:.2f})")

    # ------------------------------------------------------------------ inputs
    def on_map(self, msg: OccupancyGrid) -> None:
        try:
            occupancy_map = OccupancyMap.from_msg(msg)
        except MapError as exc:
            self.get_logger().error(f"map on {self.params.map_topic} rejected: {exc}")
            self.watchdog.map_failed(time.monotonic(), str(exc))
            self.counts["map"] += 1
            return
        if occupancy_map.frame_id != self.params.map_frame:
            self.get_logger().warning(f"map frame {occupancy_map.frame_id!r} differs from map_frame "
                                      f"{self.params.map_frame!r}; using it as {self.params.map_frame!r}")
        if len(occupancy_map.free_cells) == 0:
            self.get_logger().error(f"map on {self.params.map_topic} rejected: map has no free cell")
            self.counts["map"] += 1
            return
        self._map_generation += 1
        if self.params.sensor_model == "beam" and self.params.ray_caster in TABLE_KINDS:  # seconds: off-thread
            self.localizer.begin_map_preparation()
            self._log_table_start(occupancy_map)
            self.watchdog.map_building(time.monotonic(), "range table")
            self.map_worker.put((occupancy_map, self._map_generation, msg.header.frame_id))
        else:
            self._install_map((occupancy_map, self._map_generation, msg.header.frame_id), time.monotonic())

    def _log_table_start(self, occupancy_map: OccupancyMap) -> None:
        note = self.localizer.map_preparation(occupancy_map).note
        self.get_logger().info(f"{note}; odometry is kept meanwhile, scans cannot be used")

    def _install_map(self, item, t_put: float) -> None:
        occupancy_map, generation, frame_id = item
        t0 = time.monotonic()
        try:
            caster = self.localizer.prepare_ray_caster(occupancy_map)
        except Exception as exc:  # noqa: BLE001 - a map that cannot be prepared is reported, never fatal
            self.localizer.begin_map_preparation(False)
            self.get_logger().error(f"map on {self.params.map_topic} rejected: preparing its ray caster failed: "
                                    f"{exc!r}")
            self.watchdog.map_failed(time.monotonic(), repr(exc))
            self.counts["map"] += 1
            return
        if generation != self._map_generation:  # a newer map arrived meanwhile: it will be installed
            self.counts["map"] += 1
            return
        replacing = self.localizer.has_map
        was_ready = self.localizer.ready
        try:
            self.localizer.set_map(occupancy_map, caster)
        except MapError as exc:
            self.localizer.begin_map_preparation(False)
            self.get_logger().error(f"map on {self.params.map_topic} rejected: {exc}")
            self.watchdog.map_failed(time.monotonic(), str(exc))
            self.counts["map"] += 1
            return
        self.watchdog.map_ready(time.monotonic())
        if self.live_view is not None:
            self.live_view.set_map(occupancy_map)
        source = getattr(caster, "table_source", None)
        how = {"built": "built", "disk": "loaded from the cache", "memory": "shared with a map in memory"}.get(
            source, "")
        what = f"range table {how} in {time.monotonic() - t0:.1f} s; " if source else ""
        self.get_logger().info(f"{'new ' if replacing else ''}map {occupancy_map.width}x{occupancy_map.height} "
                               f"cells at {occupancy_map.resolution:.4f} m in frame {frame_id or '(none)'}: "
                               f"{what}{'localizing' if self.localizer.ready else 'waiting for an initial pose'}")
        if replacing and was_ready:
            if self.localizer.ready:
                self.get_logger().warning(
                    "new map: the particles are kept where they are (the new map is taken to be in the same "
                    f"frame {self.params.map_frame!r} as the previous one); if it is not, send an initial pose "
                    "or call ~/reinitialize_global_localization")
            else:
                self.get_logger().warning("new map: no particle lies in its free space: waiting for an initial "
                                          "pose")
        if self.localizer.ready:  # the first pose as soon as the map is usable, at the newest odometry's time
            last_odom = self._last_odom
            if last_odom is not None and not replacing:
                est = self.localizer.estimate_at(last_odom[0])
                if est is not None:
                    self._publish_odom_pose(est, last_odom[1])
            self._publish_particles(self._last_data_stamp or 0.0)
        self.counts["map"] += 1

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
            self.get_logger().info(f"global localization: {self.localizer.num_particles} particles spread "
                                   "over the free space of the map")
            self._publish_particles(stamp)
        return response

    @_counted("nomotion_update")
    def on_request_nomotion_update(self, request, response):
        """nav2_amcl's service: the next scan updates the filter although the car has not moved."""
        self.localizer.request_update()
        self.get_logger().info("no-motion update requested: the next scan updates the filter")
        return response

    @_counted("odom")
    def on_odometry(self, msg: Odometry) -> None:
        """The pose carried forward to this message's time t'_k on /pf/pose/odom and TF (map -> odom
        pairs it with this message's own odometry pose), then any corrections the odometry released
        (scans wait in the localizer for the odometry that reaches their time). Odometry that
        arrives before the localizer is ready (no map yet, range table being built, no initial
        pose) is kept in its history all the same."""
        self.watchdog.odom_received(time.monotonic())
        if self.localizer.map_pending and not self.localizer.has_map:
            self.watchdog.odom_waiting_for_table += 1
        t_odom = self.stamps.remember(msg.header.stamp) + self.params.odom_time_offset  # scan clock
        odom_pose = pose_from_msg(msg.pose.pose) if self._map_to_odom else None
        # with the sensor-update thread, scans this odometry releases run there (at its next scan), not here
        est = self.localizer.on_odometry(twist_from_odometry(msg), run_scans=self.scan_worker is None)
        if math.isfinite(t_odom):
            self._last_data_stamp = t_odom
            self._last_odom = (t_odom, odom_pose)
        if est is not None:  # None before a map and an initial pose (the Localizer logs that, throttled)
            self._publish_odom_pose(est, odom_pose)
        if self.scan_worker is None:  # with the sensor-update thread, that thread publishes the corrections
            self._publish_corrections()

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
        if isinstance(msg, (bytes, bytearray, memoryview)):
            msg = deserialize_message(bytes(msg), LaserScan)
        t_deser = time.monotonic()
        self.stamps.remember(msg.header.stamp)
        scan = scan_from_msg(msg)
        if self._laser_source is None or self._laser_source == "parameters" and self._laser_lookup is not None:
            self._resolve_laser_pose(scan.frame_id, t_start)
        t_conv = time.monotonic()
        t_s = self.localizer.scan_time(scan)
        if self.localizer.ready and math.isfinite(t_s):
            with self._pose_out_lock:  # the scan's way so far, until its correction is published
                self._scan_times[t_s] = (t_put, t_start, t_deser, t_conv)
                while len(self._scan_times) > SCAN_TIMES_KEPT:
                    del self._scan_times[next(iter(self._scan_times))]
        self.localizer.on_scan(scan)  # not ready: it says why (throttled)
        ignored = self.localizer.scan_ignored  # the localizer's own decision (only this thread feeds scans)
        if ignored is not None:  # no map, range table being built, or no initial pose: not usable
            building = ignored == "map pending"
            self.watchdog.scans_waiting_for_table += int(building)
            self.watchdog.scans_not_used(t_conv, 1, "while the range table was prepared" if building
                                         else f"while waiting for {self.waiting_for()}")
        if self.live_view is not None:
            self.live_view(scan, self.localizer)
        if math.isfinite(scan.stamp):
            self._last_data_stamp = scan.stamp
        self._publish_corrections()
        self.watchdog.scan_processed(time.monotonic())

    def _resolve_laser_pose(self, frame_id: str, now: float) -> None:
        """The laser pose from TF when it is there; after ``tf_timeout`` the parameters (one log line
        each); a TF arriving later still replaces the parameters."""
        p = self.params
        if self._laser_lookup is None:
            if self._laser_source is None:
                self._laser_source = "parameters"
                self.get_logger().info(f"laser pose from the parameters laser_offset_x/y/yaw ({p.laser_offset_x:.3f}, "
                                       f"{p.laser_offset_y:.3f}, {p.laser_offset_yaw:.3f}) (laser_pose_from_tf false)")
            return
        pose, why = self._laser_lookup.lookup(p.base_frame, frame_id)
        if pose is not None:
            self.localizer.set_laser_offset(pose)
            self._laser_source = "tf"
            self.watchdog.tf_ok()
            self.get_logger().info(f"laser pose from TF {p.base_frame} -> {frame_id}: ({pose[0]:.3f}, {pose[1]:.3f}, "
                                   f"{pose[2]:.3f})")
            lookup, self._laser_lookup = self._laser_lookup, None
            lookup.close()
            return
        first = self.watchdog.first_scan if self.watchdog.first_scan is not None else now
        if self._laser_source is None and now - first >= p.tf_timeout:
            self._laser_source = "parameters"
            self.get_logger().info(f"laser pose from the parameters laser_offset_x/y/yaw ({p.laser_offset_x:.3f}, "
                                   f"{p.laser_offset_y:.3f}, {p.laser_offset_yaw:.3f}): no TF {why}")
            self._laser_lookup.stop_dynamic()  # a laser mount is static: only /tf_static from now on
            if self._laser_lookup.has_data:  # TF is there but this lookup fails: a broken tree
                self.watchdog.tf_failed(now, f"{why}; using laser_offset_*")

    # ------------------------------------------------------------------ diagnostics and persistence
    def waiting_for(self) -> str:
        loc = self.localizer
        if loc.ready:
            return ""
        if not loc.has_map:
            return "the range table of the map" if loc.map_pending else f"a map on {self.params.map_topic}"
        return f"an initial pose ({self.params.initialpose_topic}, set_initial_pose or global_localization)"

    def diagnostic_status(self):
        topics = {}
        try:
            for name, types in self.get_topic_names_and_types():
                for t in types:
                    topics.setdefault(t, []).append(name)
        except Exception:  # noqa: BLE001 - a graph query must never break diagnostics
            pass
        self._report_worker_drops()
        loc = self.localizer
        status = self.watchdog.status(
            time.monotonic(), ready=loc.ready, waiting_for=self.waiting_for(), health=loc.health,
            particles=loc.num_particles, holding=loc.status != TRACKING,
            odom_topics=[t for t in topics.get(ODOMETRY_TYPE, []) if t != ODOM_POSE_TOPIC],
            scan_topics=topics.get(SCAN_TYPE, []))
        status.values["laser pose"] = {"tf": f"TF {self.params.base_frame} -> scan frame",
                                       "parameters": "laser_offset_* parameters"}.get(self._laser_source,
                                                                                      "not decided yet")
        status.values["recoveries"] = str(loc.recoveries)
        status.values["updates undone"] = f"{loc.refused_jumps} (jumped to a place the scan fits no clearly better)"
        status.values["range scale"] = f"{loc.range_scale:.4f} " + (
            "(learnt online)" if loc.range_scale_online else "(lidar_scale_to_map_scale)")
        used = loc.beams_used
        status.values["beams used"] = "no sensor update yet" if used is None else (
            f"{'n/a' if used[0] is None else used[0]} of {used[1]}"
            + (" (beam skipping)" if self.params.do_beamskip else ""))
        return status

    def _report_worker_drops(self) -> None:
        """Scans the sensor-update queue dropped since the last call, to the watchdog."""
        worker = self.scan_worker
        if worker is not None and worker.dropped > self._worker_dropped:
            self.watchdog.scans_not_used(time.monotonic(), worker.dropped - self._worker_dropped,
                                         "dropped by the full sensor-update queue")
            self._worker_dropped = worker.dropped

    def publish_diagnostics(self) -> None:
        status = self.diagnostic_status()
        stamp = self.get_clock().now().nanoseconds * 1e-9
        self.diagnostics_pub.publish(messages.diagnostic_array_msg(status, stamp, f"{self.get_name()}: localization",
                                                                   self.get_name()))
        due, cleared = self.problem_log.due(status.problems, time.monotonic())
        for problem in due:  # one call site per severity: rclpy refuses a call site whose severity changes
            if problem.level >= 2:
                self.get_logger().error(f"{LEVEL_NAMES[problem.level]}: {problem.message}")
            else:
                self.get_logger().warning(f"{LEVEL_NAMES[problem.level]}: {problem.message}")
        for key in cleared:
            self.get_logger().info(f"recovered: {key} cleared")

    def persist_pose(self) -> None:
        est = self.localizer.estimate if self.localizer is not None else None
        if est is None or not self.localizer.ready:
            return
        key = (float(est.stamp), *np.round(est.pose, 4))
        if key == self._last_persisted:
            return
        path = pose_store.pose_file(self.params.persist_pose_file)
        try:
            if pose_store.save_pose(path, est.pose, est.covariance, self.params.map_frame, est.stamp):
                self._last_persisted = key
        except OSError as exc:
            self.get_logger().warning(f"could not persist the pose to {path}: {exc}", throttle_duration_sec=30.0)

    # ------------------------------------------------------------------ outputs
    def _forward(self, t: float, last: float, stream: str) -> bool:
        """Whether an output at time t may follow one at ``last`` on a stream: newer, or more than
        TIME_JUMP older (the data's clock went back, e.g. a bag played again: the stream restarts)."""
        if t > last:
            return True
        if t < last - TIME_JUMP:
            self.get_logger().info(f"{stream}: the data's time went back by {last - t:.2f} s: its stamps "
                                   "start again")
            return True
        return False

    def _publish_odom_pose(self, est: PoseEstimate, odom_pose) -> None:
        """The pose at an odometry message's time on /pf/pose/odom and TF (stamp est.stamp)."""
        p, stamp = self.params, self.stamps.lookup(est.stamp)
        msg = messages.odometry_msg(est.pose, est.covariance, stamp, p.map_frame, p.particle_filter_frame)
        if msg is None:
            self.get_logger().warning("non-finite estimate not published", throttle_duration_sec=5.0)
            return
        tf = None
        if self.tf is not None and not self._map_to_odom:
            tf = messages.transform_msg(est.pose, stamp, p.map_frame, p.particle_filter_frame)
        elif self.tf is not None and odom_pose is not None:
            tf = messages.transform_msg(messages.map_to_odom(est.pose, odom_pose), stamp, p.map_frame, p.odom_frame)
        with self._odom_out_lock:  # stamps only move forward (no TF_REPEATED_DATA)
            if not self._forward(est.stamp, self._last_odom_out, ODOM_POSE_TOPIC):
                return
            self._last_odom_out = est.stamp
            self.pose_pub.publish(msg)
            if tf is not None:
                self.tf.send([tf])

    def _publish_corrections(self) -> int:
        """Each sensor-corrected estimate the localizer made since the last call, newer than the
        last one on /pf/pose, on /pf/pose at its scan's time; then the cloud and the health.
        Returns how many were published."""
        corrections = self.localizer.take_corrections()
        if not corrections:
            return 0
        p = self.params
        with self._pose_out_lock:
            published = 0
            for est in corrections:
                if not self._forward(est.stamp, self._last_pose_out, p.pose_topic):
                    continue
                t_ready = time.monotonic()
                msg = messages.pose_with_covariance_msg(est.pose, est.covariance, self.stamps.lookup(est.stamp),
                                                        p.map_frame)
                if msg is None:
                    self.get_logger().warning("non-finite estimate not published", throttle_duration_sec=5.0)
                    continue
                self._last_pose_out = est.stamp
                self.pose_cov_pub.publish(msg)
                published += 1
                now = time.monotonic()
                way = self._scan_times.pop(est.stamp, None)  # (put, start, deserialized, converted)
                phases = None if way is None else {
                    "wait": way[1] - way[0], "deserialize": way[2] - way[1], "convert": way[3] - way[2],
                    "update": t_ready - way[3], "publish": now - t_ready}
                self.watchdog.sensor_update(now, phases)
            if published:
                self._publish_particles(self._last_pose_out)
                health = messages.health_msg(self.localizer.health)
                if health is not None:  # NaN while the cloud is still spread (global localization)
                    self.health_pub.publish(health)
        return published

    def _publish_particles(self, stamp: float) -> None:
        if self.params.max_particles_published > 0 and _subscribed(self.particles_pub):
            self.particles_pub.publish(messages.pose_array_cdr(
                self.localizer.particles(), self.stamps.lookup(stamp), self.params.map_frame,
                self.params.max_particles_published))


class ParticleFilterNode(LocalizationMixin, Node):
    """The plain node: configured and active from construction."""

    def __init__(self, **node_kwargs):
        super().__init__(NODE_NAME, **node_kwargs)
        self._declare_or_destroy()
        self._configure()
        self._activate()

    def destroy_node(self):
        self._shutdown_wiring()
        return super().destroy_node()


# ---------------------------------------------------------------------------------- command line
USAGE = """usage: {prog} [-h] [--ros-args --params-file FILE -p NAME:=VALUE ...]

The particle filter localizer node (Monte Carlo localization in a known map).

Inputs: /map (nav_msgs/OccupancyGrid), /scan (sensor_msgs/LaserScan), /odom (nav_msgs/Odometry),
/initialpose (geometry_msgs/PoseWithCovarianceStamped). Outputs: /pf/pose
(PoseWithCovarianceStamped), /pf/pose/odom (Odometry), /pf/particles, /pf/health, /diagnostics, TF.
Services: ~/reinitialize_global_localization, request_nomotion_update (std_srvs/Empty).

--params-file accepts a path or the name of a file in the package's config/ (params, real_params).
Examples:
  {prog} --ros-args --params-file real_params -p odom_topic:=/vesc/odom
  {prog} --ros-args -p set_initial_pose:=true -p initial_pose.x:=1.0 -p initial_pose.y:=2.0

Parameters (name = default):
{params}

Documentation: docs/node.md in the package.
"""


def usage(prog: str = NODE_NAME) -> str:
    lines = "\n".join(f"  {p.name} = {p.default!r}" for p in PARAMETERS)
    return USAGE.format(prog=prog, params=lines)


def _print_help(text: str) -> None:
    """Print the usage; a reader that stops early (``particle_filter -h | head``) is no error."""
    try:
        print(text, flush=True)
    except BrokenPipeError:
        devnull = os.open(os.devnull, os.O_WRONLY)  # Python flushes stdout again at exit: not into the pipe
        os.dup2(devnull, sys.stdout.fileno())


def _node_identity(ros: list[str]) -> tuple[str, str]:
    """(namespace, node name) after the ``-r __node:=`` / ``-r __ns:=`` remappings of the ROS arguments."""
    name, namespace = NODE_NAME, "/"
    for i, arg in enumerate(ros[:-1]):
        if arg in ("-r", "--remap"):
            key, _, value = ros[i + 1].partition(":=")
            if key in ("__node", "__name") and value:
                name = value
            elif key == "__ns" and value:
                namespace = value
    return namespace, name


def check_params_file(path, ros: list[str]) -> str:
    """Why a parameter file cannot configure this node ("" when it can): unreadable, or no section
    that applies to the node (a misspelt node name would leave every parameter at its default)."""
    import yaml

    from localization.core.parameters import node_sections, section_error
    try:
        doc = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError) as exc:
        return f"cannot read parameter file {path}: {exc}".splitlines()[0]
    keys = list(doc) if isinstance(doc, dict) else []
    namespace, name = _node_identity(ros)
    return "" if node_sections(keys, name, namespace) else section_error(path, keys, name)


def prepare_args(argv: list[str]) -> tuple[list[str] | None, int | None]:
    """(arguments for rclpy, None) or (None, exit code) after ``--help`` or a bad command line: an
    argument outside ``--ros-args`` (exit 2, with a hint), a missing parameter file, or one without
    a section for this node (exit 1). A ``--params-file`` given by name (``real_params`` or
    ``real_params.yaml``) is looked up in the package's config/ when it is not a file here."""
    from localization.core.paths import config_dir, resolve_params_path, split_ros_args
    prog = os.path.basename(argv[0]) if argv else NODE_NAME
    own, ros = split_ros_args(argv[1:])
    if any(arg in ("-h", "--help") for arg in own):
        _print_help(usage(prog))
        return None, 0
    if own:
        print(f"{prog}: error: unrecognized arguments: {' '.join(own)} (ROS arguments go after --ros-args, e.g. "
              f"{prog} --ros-args --params-file real_params -p num_particles:=1000; {prog} --help lists the "
              "parameters)", file=sys.stderr)
        return None, 2
    out = list(argv[:1])
    i = 0
    while i < len(ros):
        if ros[i] != "--params-file":
            out.append(ros[i])
            i += 1
            continue
        if i + 1 >= len(ros):
            print(f"{prog}: error: --params-file needs a file", file=sys.stderr)
            return None, 2
        path = resolve_params_path(ros[i + 1])
        if not path.is_file():
            names = ", ".join(sorted(f.stem for f in config_dir().glob("*.yaml"))) or "none"
            print(f"{prog}: error: parameter file not found: {ros[i + 1]} (a path, or a name in {config_dir()}: "
                  f"{names})", file=sys.stderr)
            return None, 1
        problem = check_params_file(path, ros)
        if problem:
            print(f"{prog}: error: {problem}", file=sys.stderr)
            return None, 1
        out += ["--params-file", str(path)]
        i += 2
    return out, None


def spin_node(node_factory, args=None) -> int:
    """Init rclpy (with our own SIGINT/SIGTERM handling, so the context is still valid while the node
    shuts down and logs), spin ``node_factory()`` until SIGINT or SIGTERM, shut down cleanly (exit
    code 0). The executor waits at most SPIN_WAKE_S at a time, so a signal is acted on within that
    even when nothing else wakes it (a lifecycle node unconfigured, inactive or finalized has no
    timer and no subscription)."""
    import signal

    from rclpy.signals import SignalHandlerOptions

    argv = list(sys.argv if args is None else args)
    argv, code = prepare_args(argv)
    if argv is None:
        return code
    # The executor thread and the sensor-update thread share the GIL: a thread waiting for it gets it
    # after at most the switch interval (5 ms by default), a direct addition to the scan -> pose latency.
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
    try:
        rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as exc:  # noqa: BLE001 - e.g. a malformed --ros-args: one line, no traceback
        print(f"{NODE_NAME}: error: {exc}".splitlines()[0], file=sys.stderr)
        return 1
    executor = SingleThreadedExecutor()
    stop = threading.Event()

    def on_signal(signum, frame):  # noqa: ARG001 - the loop below ends after the current callback
        stop.set()

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    node = None
    try:
        try:
            node = node_factory()
        except ParameterError:
            return 1
        executor.add_node(node)
        while not stop.is_set() and rclpy.ok():
            executor.spin_once(timeout_sec=SPIN_WAKE_S)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        executor.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


def main(args=None) -> int:
    return spin_node(ParticleFilterNode, args)


if __name__ == "__main__":
    sys.exit(main())
