"""The node's /diagnostics: the watchdog's status (``core.watchdog``) with the localizer's figures.

Every ``diagnostics_period`` the node publishes one ``diagnostic_msgs/DiagnosticStatus``; each
problem (no odometry while scans arrive, no scans, no map, TF, scans not used, scans disagree,
lost) is logged when it appears and every 5 s while it lasts, and once more when it clears.
The checks themselves are ROS-free (``core.watchdog.Watchdog``, tested with a fake clock); this
module only adds what the node knows (the topics present, the laser pose's source, the sensor
update queue) and turns the status into a message and log lines.
"""
from __future__ import annotations

import time

from localization.core.localizer.recovery import TRACKING
from localization.core.watchdog import LEVEL_NAMES, ProblemLog, Status, Watchdog
from localization.ros import messages
from localization.ros.outputs import ODOM_POSE_TOPIC

ODOMETRY_TYPE, SCAN_TYPE = "nav_msgs/msg/Odometry", "sensor_msgs/msg/LaserScan"


class Diagnostics:
    """The status of a configured node, its message and its log lines."""

    def __init__(self, node, params, watchdog: Watchdog):
        self.node, self.params, self.watchdog = node, params, watchdog
        self.problem_log = ProblemLog()
        self._worker_dropped = 0  # scans the sensor-update queue dropped, already reported

    def waiting_for(self, loc) -> str:
        """What the localizer waits for ("" when it localizes)."""
        if loc.ready:
            return ""
        if not loc.has_map:
            return "the range table of the map" if loc.map_pending else f"a map on {self.params.map_topic}"
        return f"an initial pose ({self.params.initialpose_topic}, set_initial_pose or global_localization)"

    def _topics(self) -> dict:
        topics = {}
        try:
            for name, types in self.node.get_topic_names_and_types():
                for t in types:
                    topics.setdefault(t, []).append(name)
        except Exception:  # noqa: BLE001 - a graph query must never break diagnostics
            pass
        return topics

    def status(self, loc, laser_pose: str, scan_worker=None) -> Status:
        """The watchdog's status now, with the localizer's figures as key values."""
        topics = self._topics()
        self.report_worker_drops(scan_worker)
        status = self.watchdog.status(
            time.monotonic(), ready=loc.ready, waiting_for=self.waiting_for(loc), health=loc.health,
            particles=loc.num_particles, holding=loc.status != TRACKING,
            odom_topics=[t for t in topics.get(ODOMETRY_TYPE, []) if t != ODOM_POSE_TOPIC],
            scan_topics=topics.get(SCAN_TYPE, []))
        status.values["laser pose"] = laser_pose
        status.values["recoveries"] = str(loc.recoveries)
        status.values["updates undone"] = f"{loc.refused_jumps} (jumped to a place the scan fits no clearly better)"
        status.values["range scale"] = f"{loc.range_scale:.4f} " + (
            "(learnt online)" if loc.range_scale_online else "(lidar_scale_to_map_scale)")
        used = loc.beams_used
        status.values["beams used"] = "no sensor update yet" if used is None else (
            f"{'n/a' if used[0] is None else used[0]} of {used[1]}"
            + (" (beam skipping)" if self.params.do_beamskip else ""))
        return status

    def publish(self, status: Status, publish) -> None:
        """``publish(DiagnosticArray)`` the status; log the problems that are due and those cleared."""
        node = self.node
        stamp = node.get_clock().now().nanoseconds * 1e-9
        publish(messages.diagnostic_array_msg(status, stamp, f"{node.get_name()}: localization", node.get_name()))
        due, cleared = self.problem_log.due(status.problems, time.monotonic())
        log = node.get_logger()
        for problem in due:  # one call site per severity: rclpy refuses a call site whose severity changes
            if problem.level >= 2:
                log.error(f"{LEVEL_NAMES[problem.level]}: {problem.message}")
            else:
                log.warning(f"{LEVEL_NAMES[problem.level]}: {problem.message}")
        for key in cleared:
            log.info(f"recovered: {key} cleared")

    def report_worker_drops(self, worker) -> None:
        """Scans the sensor-update queue dropped since the last call, to the watchdog."""
        if worker is not None and worker.dropped > self._worker_dropped:
            self.watchdog.scans_not_used(time.monotonic(), worker.dropped - self._worker_dropped,
                                         "dropped by the full sensor-update queue")
            self._worker_dropped = worker.dropped

    def run_summary(self, worker) -> str:
        """The run's statistics, one line (logged at cleanup and shutdown)."""
        self.report_worker_drops(worker)
        w = self.watchdog
        return (f"scans: {w.scans_received} received, {w.scans_processed} processed, {w.scans_dropped} not used "
                f"({w.scans_waiting_for_table} while the range table was prepared); {w.sensor_updates} sensor "
                f"updates; odometry: {w.odom_count} received ({w.odom_waiting_for_table} while the range table was "
                f"prepared, kept); scan -> pose: {w.run_summary()}")
