"""The one loop that feeds messages to a ``Localizer`` and logs what the node would publish.

``localization-replay`` (bag messages), the robustness benchmark (simulated recordings) and the
tuner all drive the core through a ``Feeder``: each odometry twist or scan goes to the
Localizer in stamp order, and the log keeps every estimate (what the node publishes: after each
odometry message and each sensor update), the filter's health after each sensor update, and the
time spent inside the Localizer per call.
"""
from __future__ import annotations

import math
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from localization.core.localizer import Localizer, PoseEstimate
from localization.core.odometry import TwistData
from localization.core.scan import ScanData


@dataclass
class FeedLog:
    """What came out of the Localizer while feeding it. Stamps are on the scan clock (the time each
    pose describes); ``est_t`` never goes backwards (what the node publishes on /pf/pose/odom)."""

    est_t: list = field(default_factory=list)  # s, time of each published estimate (non-decreasing)
    est_poses: list = field(default_factory=list)  # (3,) each
    corrected_t: list = field(default_factory=list)  # s, each sensor-corrected estimate's scan time
    corrected_poses: list = field(default_factory=list)  # (3,) each
    health_t: list = field(default_factory=list)  # s, after each sensor update with a finite health
    health: list = field(default_factory=list)
    particles_t: list = field(default_factory=list)  # s, after each sensor update
    particles: list = field(default_factory=list)  # the particle count then (varies with adaptive_particles)
    sensor_times: list = field(default_factory=list)  # s inside the call that made each sensor update
    motion_times: list = field(default_factory=list)  # s inside on_odometry, per estimate
    filter_time: float = 0.0  # s inside the Localizer (all calls)
    counts: dict = field(default_factory=lambda: {"scans": 0, "odometry": 0, "initial_poses": 0,
                                                  "sensor_updates": 0, "motion_updates": 0})

    def estimates(self) -> tuple[np.ndarray, np.ndarray]:
        return np.asarray(self.est_t, dtype=float), np.asarray(self.est_poses, dtype=float).reshape(-1, 3)

    def corrections(self) -> tuple[np.ndarray, np.ndarray]:
        return np.asarray(self.corrected_t, dtype=float), np.asarray(self.corrected_poses, dtype=float).reshape(-1, 3)


class Feeder:
    """Feeds one Localizer; ``log`` collects the results."""

    def __init__(self, localizer: Localizer):
        self.localizer = localizer
        self.log = FeedLog()

    def _timed(self, call, arg):
        t0 = time.perf_counter()
        est = call(arg)
        dt = time.perf_counter() - t0
        self.log.filter_time += dt
        return est, dt

    def _publish(self, est: PoseEstimate | None) -> None:
        """A pose goes out only when it is not older than the last one (as the node does)."""
        if est is not None and (not self.log.est_t or est.stamp >= self.log.est_t[-1]):
            self.log.est_t.append(est.stamp)
            self.log.est_poses.append(np.array(est.pose, dtype=float))

    def _corrections(self, dt: float) -> None:
        """The sensor updates this call made (a scan may have waited for this odometry)."""
        for est in self.localizer.take_corrections():
            self.log.sensor_times.append(dt)
            self.log.counts["sensor_updates"] += 1
            self.log.corrected_t.append(est.stamp)
            self.log.corrected_poses.append(np.array(est.pose, dtype=float))
            self.log.particles_t.append(est.stamp)
            self.log.particles.append(self.localizer.num_particles)
            if math.isfinite(self.localizer.health):
                self.log.health_t.append(est.stamp)
                self.log.health.append(self.localizer.health)
            self._publish(est)

    def odometry(self, twist: TwistData) -> PoseEstimate | None:
        self.log.counts["odometry"] += 1
        est, dt = self._timed(self.localizer.on_odometry, twist)
        self._corrections(dt)
        if est is not None:
            self.log.motion_times.append(dt)
            self.log.counts["motion_updates"] += 1
        self._publish(est)
        return est

    def scan(self, scan: ScanData) -> PoseEstimate | None:
        self.log.counts["scans"] += 1
        est, dt = self._timed(self.localizer.on_scan, scan)
        self._corrections(dt)
        return est

    def initial_pose(self, pose, covariance, stamp: float) -> None:
        self.log.counts["initial_poses"] += 1
        t0 = time.perf_counter()
        self.localizer.set_initial_pose(pose, covariance, stamp)
        self.log.filter_time += time.perf_counter() - t0

    def feed(self, events) -> FeedLog:
        """Feed an iterable of ``TwistData`` / ``ScanData`` in order."""
        for event in events:
            if isinstance(event, ScanData):
                self.scan(event)
            else:
                self.odometry(event)
        return self.log


def recording_events(rec, t_offset: float = 0.0) -> Iterator[TwistData | ScanData]:
    """A simulated ``Recording``'s odometry and scans in stamp order (odometry first at equal stamps)."""
    cfg = rec.cfg
    odom_t = rec.odometry.t + t_offset
    scan_t = rec.scan_t + t_offset
    events = np.concatenate([np.stack([odom_t, np.zeros_like(odom_t), np.arange(len(odom_t))], 1),
                             np.stack([scan_t, np.ones_like(scan_t), np.arange(len(scan_t))], 1)])
    events = events[np.lexsort((events[:, 1], events[:, 0]))]
    twist = rec.odometry.twist
    for t, kind, k in events:
        k = int(k)
        if kind == 0:
            yield TwistData(float(t), *(float(v) for v in twist[k]))
        else:
            yield ScanData(float(t), rec.scan_ranges[k], cfg.angle_min, cfg.angle_max, rec.scan_angle_increment,
                           cfg.range_min, cfg.range_max, time_increment=rec.scan_time_increment,
                           scan_time=1.0 / cfg.scan_rate)
