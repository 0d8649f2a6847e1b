"""The node's outputs: publishers, one publish rule per stream, and the message builders' calls.

    /pf/pose/odom, TF   x̂ ⊕ Δ(t_a, t'_k) at t'_k = t_k + odom_time_offset, on each odometry message k
                        (``publish_odom_pose``)
    /pf/pose            x̂(t_s) at the scan's time t_s, each sensor-corrected estimate once
                        (``publish_corrections``), then the cloud on /pf/particles (at the time of the
                        newest correction published with it) and the health on /pf/health

The pose, odometry, TF and cloud messages are published already serialized (``ros.cdr``): no Python
message object is built per odometry message or scan.

Each stream only moves forward (``core.publish_rule``: an output as old as, or older than, the last
one on its stream is not published, unless the data's clock went back by more than TIME_JUMP: the
stream restarts). Odometry and scans may be handled on two threads (``sensor_update_thread``): each
stream's rule and its publishing are under that stream's lock.
"""
from __future__ import annotations

import threading
import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from std_msgs.msg import Float32

from localization.core.localizer.timeline import PoseEstimate
from localization.core.publish_rule import ForwardInTime, Verdict
from localization.ros import cdr, messages
from localization.ros.tf_broadcaster import TransformBroadcaster

ODOM_POSE_TOPIC = "/pf/pose/odom"  # nav_msgs/Odometry (the course's output)
PARTICLES_TOPIC = "/pf/particles"
HEALTH_TOPIC = "/pf/health"  # std_msgs/Float32: scan-map agreement of the estimate (localization.health)
DIAGNOSTICS_TOPIC = "/diagnostics"


def _subscribed(publisher) -> bool:
    """Whether anyone listens (True for stand-ins without the count, e.g. test recorders)."""
    count = getattr(publisher, "get_subscription_count", None)
    return count is None or count() > 0


class Outputs:
    """Publishers of a configured node; ``destroy`` releases them (the node stays)."""

    def __init__(self, node, params, localizer, stamps, watchdog, latency):
        self.node, self.params, self.localizer = node, params, localizer
        self.stamps, self.watchdog, self.latency = stamps, watchdog, latency
        self.log = node.get_logger()
        self.pose_pub = node.create_publisher(Odometry, ODOM_POSE_TOPIC, 10)
        self.pose_cov_pub = node.create_publisher(PoseWithCovarianceStamped, params.pose_topic, 10)
        self.particles_pub = node.create_publisher(PoseArray, PARTICLES_TOPIC, 5)
        self.health_pub = node.create_publisher(Float32, HEALTH_TOPIC, 10)
        self.diagnostics_pub = node.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, 10)
        self.tf = None if params.publish_tf == "none" else TransformBroadcaster(node)
        self.map_to_odom = params.publish_tf == "map_to_odom"  # only then is the odometry pose needed
        self._odom_lock = threading.Lock()  # /pf/pose/odom and TF: one stamp order
        self._odom_rule = ForwardInTime()
        self._pose_lock = threading.Lock()  # /pf/pose, /pf/particles, /pf/health
        self._pose_rule = ForwardInTime()

    def _admit(self, rule: ForwardInTime, t: float, stream: str) -> bool:
        last = rule.last
        verdict = rule.admit(t)
        if verdict is Verdict.RESTART:
            self.log.info(f"{stream}: the data's time went back by {last - t:.2f} s: its stamps start again")
        return verdict.published

    def publish_odom_pose(self, est: PoseEstimate, odom_pose) -> None:
        """The pose at an odometry message's time on /pf/pose/odom and TF (stamp est.stamp);
        ``odom_pose``: that message's own pose (map -> odom needs it)."""
        p, stamp = self.params, self.stamps.lookup(est.stamp)
        msg = cdr.odometry_cdr(est.pose, est.covariance, stamp, p.map_frame, p.particle_filter_frame)
        if msg is None:
            self.log.warning("non-finite estimate not published", throttle_duration_sec=5.0)
            return
        tf = None
        if self.tf is not None and not self.map_to_odom:
            tf = cdr.tf_message_cdr(est.pose, stamp, p.map_frame, p.particle_filter_frame)
        elif self.tf is not None and odom_pose is not None:
            tf = cdr.tf_message_cdr(messages.map_to_odom(est.pose, odom_pose), stamp, p.map_frame, p.odom_frame)
        with self._odom_lock:  # stamps only move forward (no TF_REPEATED_DATA)
            if not self._admit(self._odom_rule, est.stamp, ODOM_POSE_TOPIC):
                return
            self.pose_pub.publish(msg)
            if tf is not None:
                self.tf.send_serialized(tf)

    def publish_corrections(self) -> int:
        """Each sensor-corrected estimate the localizer made since the last call, newer than the
        last one on /pf/pose, on /pf/pose at its scan's time; then the cloud and the health.
        Returns how many were published."""
        corrections = self.localizer.take_corrections()
        if not corrections:
            return 0
        p = self.params
        with self._pose_lock:
            published = 0
            for est in corrections:
                if not self._pose_rule.judge(est.stamp).published:
                    continue
                ready = time.monotonic()
                msg = cdr.pose_with_covariance_cdr(est.pose, est.covariance, self.stamps.lookup(est.stamp),
                                                   p.map_frame)
                if msg is None:
                    self.log.warning("non-finite estimate not published", throttle_duration_sec=5.0)
                    continue
                self._admit(self._pose_rule, est.stamp, p.pose_topic)
                self.pose_cov_pub.publish(msg)
                published += 1
                now = time.monotonic()
                self.watchdog.sensor_update(now, self.latency.phases(est.stamp, ready, now))
            if published:
                self.publish_particles(self._pose_rule.last)
                health = messages.health_msg(self.localizer.health)
                if health is not None:  # NaN while the cloud is still spread (global localization)
                    self.health_pub.publish(health)
        return published

    def publish_particles(self, stamp: float) -> None:
        """The cloud (at most ``max_particles_published``), when anyone listens."""
        if self.params.max_particles_published > 0 and _subscribed(self.particles_pub):
            self.particles_pub.publish(cdr.pose_array_cdr(
                self.localizer.particles(), self.stamps.lookup(stamp), self.params.map_frame,
                self.params.max_particles_published))

    def publish_diagnostics(self, array: DiagnosticArray) -> None:
        self.diagnostics_pub.publish(array)

    def destroy(self) -> None:
        """Destroy the publishers (stand-ins swapped in by tests are left alone)."""
        from rclpy.publisher import Publisher
        for pub in (self.pose_pub, self.pose_cov_pub, self.particles_pub, self.health_pub, self.diagnostics_pub):
            if isinstance(pub, Publisher):
                self.node.destroy_publisher(pub)
        if isinstance(self.tf, TransformBroadcaster):
            self.tf.destroy()
