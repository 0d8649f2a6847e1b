"""The one loop that feeds messages to a ``Localizer`` and logs what the node would publish.

``localization-replay`` (bag messages), the tuner (the same bags, read once), the robustness and
models benchmarks (simulated recordings) all drive the core through ``Feeder.run``: each odometry
twist, scan or initial pose goes to the Localizer in stamp order, and the log keeps every estimate
(what the node publishes: after each odometry message and each sensor update, forward in time by
the node's publish rule, ``core.publish_rule``, one pose per instant: the newest knowledge of it),
every sensor-corrected estimate, the filter's health after each sensor update, the time spent
inside the Localizer per call, the estimate at each scan's own time (the scan track, what a
per-scan reference is compared with) and, with a scorer (``make_scorer``: the one way the
evaluation builds it), the scan–map agreement of that estimate::

    t_k = localizer.scan_time(scan_k) (scan clock),   a_k = agreement(x̂(t_k), scan_k),
    x̂(t_k) = localizer.estimate_at(t_k) once odometry has reached t_k (the scan's sensor update,
    if any, is then done), or at the end of the feed
"""
from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np

from localization.core.localizer import Localizer, PoseEstimate, ScanResult
from localization.core.localizer.health import AgreementScorer
from localization.core.models.beam_kernels import choose_threading_layer
from localization.core.occupancy_map import OccupancyMap
from localization.core.odometry import TwistData
from localization.core.parameters import Parameters
from localization.core.publish_rule import ForwardInTime, Verdict
from localization.core.scan import ScanData, beam_angles

choose_threading_layer("omp")  # a feed runs its sensor updates back to back, with no idle between them


def make_scorer(occupancy_map: OccupancyMap, params: Parameters) -> AgreementScorer:
    """The scan–map agreement scorer of the evaluation (replay, tuner, benchmarks): the map, the
    laser mount (``laser_offset_x/y/yaw``) and the lidar range scale (``lidar_scale_to_map_scale``)
    of ``params``."""
    return AgreementScorer(occupancy_map, (params.laser_offset_x, params.laser_offset_y, params.laser_offset_yaw),
                           range_scale=params.lidar_scale_to_map_scale)


@dataclass
class InitialPose:
    """An initial pose (``/initialpose``) among the events fed, given to ``Localizer.set_initial_pose``."""

    stamp: float  # s, the message's header stamp
    pose: np.ndarray  # (3,) x, y, θ in the map frame
    covariance: np.ndarray | None  # (3, 3) over x, y, θ, or None


@dataclass
class FeedLog:
    """What came out of the Localizer while feeding it. Stamps are on the scan clock (the time each
    pose describes); ``est_t`` goes forward (``core.publish_rule``, as the node publishes; it goes back only
    where the data's clock went back by more than TIME_JUMP: the stream restarts)."""

    est_t: list = field(default_factory=list)  # s, time of each published estimate (increasing)
    est_poses: list = field(default_factory=list)  # (3,) each
    corrected_t: list = field(default_factory=list)  # s, each sensor-corrected estimate's scan time
    corrected_poses: list = field(default_factory=list)  # (3,) each
    health_t: list = field(default_factory=list)  # s, after each sensor update with a finite health
    health: list = field(default_factory=list)
    particles_t: list = field(default_factory=list)  # s, after each sensor update
    particles: list = field(default_factory=list)  # the particle count then (varies with adaptive_particles)
    sensor_times: list = field(default_factory=list)  # s inside the call that made each sensor update
    motion_times: list = field(default_factory=list)  # s inside on_odometry, per estimate
    scan_t: list = field(default_factory=list)  # s, scan clock: each scan's time t_k (once it has an estimate)
    scan_poses: list = field(default_factory=list)  # (3,) x̂(t_k): the estimate at that scan's time
    agreement_t: list = field(default_factory=list)  # s, scan clock: each scored scan's time t_k
    agreement: list = field(default_factory=list)  # scan–map agreement of x̂(t_k) (with a scorer; finite only)
    costs: list = field(default_factory=list)  # core.cost.UpdateCost of each scan through the pipeline, in order
    filter_time: float = 0.0  # s inside the Localizer (all calls)
    init_t: float | None = None  # s, stamp of the first initialisation (Feeder.run)
    initial_pose: np.ndarray | None = None  # (3,) the first initial pose (None: global localization or none)
    cut: bool = False  # Feeder.run stopped early: the filter time exceeded max_filter_time
    counts: dict = field(default_factory=lambda: {"scans": 0, "odometry": 0, "initial_poses": 0,
                                                  "sensor_updates": 0, "motion_updates": 0})

    def estimates(self) -> tuple[np.ndarray, np.ndarray]:
        return np.asarray(self.est_t, dtype=float), np.asarray(self.est_poses, dtype=float).reshape(-1, 3)

    def corrections(self) -> tuple[np.ndarray, np.ndarray]:
        return np.asarray(self.corrected_t, dtype=float), np.asarray(self.corrected_poses, dtype=float).reshape(-1, 3)

    def scan_track(self) -> tuple[np.ndarray, np.ndarray]:
        """The estimate at each scan's time (t_k, x̂(t_k)): what a per-scan reference is compared with."""
        return np.asarray(self.scan_t, dtype=float), np.asarray(self.scan_poses, dtype=float).reshape(-1, 3)


START_FROM_EVENTS = "events"  # Feeder.run: the events' InitialPose items initialise the filter
START_GLOBAL = "global"  # Feeder.run: global localization at the first input


class Feeder:
    """Feeds one Localizer; ``log`` collects the results. With a ``scorer`` each scan's agreement
    is logged at the scan's time (module doc)."""

    def __init__(self, localizer: Localizer, scorer: AgreementScorer | None = None):
        self.localizer = localizer
        self.scorer = scorer
        self.log = FeedLog()
        self._pending: deque[tuple[float, ScanData]] = deque()  # scans waiting to be scored, (t_k, scan)
        self._odometry_until = -math.inf  # s, scan clock: the newest odometry time returned
        self._angles: dict = {}
        self._rule = ForwardInTime()  # the node's publish rule, on the estimates logged as published

    def _score_until(self, t: float) -> None:
        """Log x̂(t_k) (and score it, with a scorer) for the waiting scans whose time odometry (or a
        correction) has reached, t_k <= t, in the order they came (a non-finite t_k: dropped)."""
        ready = [p for p in self._pending if not p[0] > t]
        if not ready:
            return
        self._pending = deque(p for p in self._pending if p[0] > t)
        for t_k, scan in ready:
            est = self.localizer.estimate_at(t_k) if math.isfinite(t_k) else None
            if est is None or not np.all(np.isfinite(est.pose)):
                continue
            self.log.scan_t.append(t_k)
            self.log.scan_poses.append(np.array(est.pose, dtype=float))
            if self.scorer is None:
                continue
            key = (np.size(scan.ranges), scan.angle_min, scan.angle_max, scan.angle_increment)
            if key not in self._angles:
                self._angles[key] = beam_angles(*key)
            a = self.scorer.score(est.pose, scan.ranges, self._angles[key], scan.range_min, scan.range_max)
            if math.isfinite(a):
                self.log.agreement_t.append(t_k)
                self.log.agreement.append(a)

    def _timed(self, call, arg):
        t0 = time.perf_counter()
        est = call(arg)
        dt = time.perf_counter() - t0
        self.log.filter_time += dt
        return est, dt

    def _publish(self, est: PoseEstimate | None) -> None:
        """A pose goes out by the node's publish rule (``core.publish_rule``); a second estimate of the
        instant logged last (a correction at an odometry message's time) replaces it."""
        if est is None:
            return
        verdict = self._rule.admit(est.stamp)
        if verdict is Verdict.SAME and self.log.est_t:
            self.log.est_poses[-1] = np.array(est.pose, dtype=float)
        elif verdict.published:
            self.log.est_t.append(est.stamp)
            self.log.est_poses.append(np.array(est.pose, dtype=float))

    def _corrections(self, dt: float) -> None:
        """The sensor updates this call made (a scan may have waited for this odometry)."""
        self.log.costs.extend(self.localizer.take_costs())
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
            self._score_until(est.stamp)

    def odometry(self, twist: TwistData) -> PoseEstimate | None:
        self.log.counts["odometry"] += 1
        est, dt = self._timed(self.localizer.on_odometry, twist)
        self._corrections(dt)
        if est is not None:
            self.log.motion_times.append(dt)
            self.log.counts["motion_updates"] += 1
            self._odometry_until = max(self._odometry_until, est.stamp)
            self._score_until(self._odometry_until)
        self._publish(est)
        return est

    def scan(self, scan: ScanData) -> ScanResult:
        """What the Localizer did with the scan (ignored and why, or the scans it used)."""
        self.log.counts["scans"] += 1
        self._pending.append((self.localizer.scan_time(scan), scan))
        result, dt = self._timed(self.localizer.on_scan, scan)
        self._corrections(dt)
        self._score_until(self._odometry_until)  # a scan odometry had already reached is used at once
        return result

    def initial_pose(self, pose, covariance, stamp: float) -> None:
        self.log.counts["initial_poses"] += 1
        t0 = time.perf_counter()
        self.localizer.set_initial_pose(pose, covariance, stamp)
        self.log.filter_time += time.perf_counter() - t0

    def feed(self, events) -> FeedLog:
        """Feed an iterable of ``TwistData`` / ``ScanData`` / ``InitialPose`` in order (the
        Localizer initialised beforehand, or by the events)."""
        return self.run(events)

    def run(self, events: Iterable, start=START_FROM_EVENTS, on_scan: Callable | None = None,
            max_filter_time: float = math.inf) -> FeedLog:
        """Feed ``events`` (``TwistData``, ``ScanData``, ``InitialPose``) in order, then ``end``.

        ``start``: ``START_FROM_EVENTS`` (the events' initial poses, fed where they occur),
        ``START_GLOBAL`` (global localization at the first odometry or scan's stamp), or a pose
        (x, y, θ) set at the first odometry or scan's stamp. ``on_scan(scan, localizer)`` is called
        after each scan. The feed stops (``log.cut``) once the time spent inside the Localizer
        exceeds ``max_filter_time`` seconds."""
        started = isinstance(start, str) and start == START_FROM_EVENTS
        for event in events:
            if isinstance(event, InitialPose):
                self.initial_pose(event.pose, event.covariance, event.stamp)
                if self.log.init_t is None:
                    self.log.init_t, self.log.initial_pose = event.stamp, np.asarray(event.pose, dtype=float)
                continue
            if not started:
                self._start(start, event.stamp)
                started = True
            if isinstance(event, ScanData):
                self.scan(event)
                if on_scan is not None:
                    on_scan(event, self.localizer)
                if self.log.filter_time > max_filter_time:
                    self.log.cut = True
                    return self.log
            else:
                self.odometry(event)
        self.end()
        return self.log

    def _start(self, start, stamp: float) -> None:
        """Initialise at the first input (``run``'s ``start``: global, or a pose)."""
        self.log.init_t = stamp
        if isinstance(start, str):
            if start != START_GLOBAL:
                raise ValueError(f"start must be {START_FROM_EVENTS!r}, {START_GLOBAL!r} or a pose, got {start!r}")
            self.localizer.initialize_global(stamp)
            return
        pose = np.asarray(start, dtype=float).reshape(3)
        self.localizer.set_initial_pose(pose, None, stamp)
        self.log.initial_pose = pose

    def end(self) -> None:
        """The end of the recording: scans still waiting for odometry are used now, and scored."""
        t0 = time.perf_counter()
        self.localizer.flush()
        self._corrections(time.perf_counter() - t0)
        self._score_until(math.inf)


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
