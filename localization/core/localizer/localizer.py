"""The localizer: the one object the node, replay, the tuner and the benchmarks hold.

It takes the inputs and hands each to the part whose one job it is:

    OdometryTimeline (timeline)   odometry on the scan clock; the pose at any time (anchor ⊕ Δ)
    ScanQueue (policies)          a scan waits for the odometry that covers its time
    ScanPipeline (pipeline)       one scan: move, gate, beams, deskew, weigh, resample, estimate, decide
    check_initial_pose            an initial pose checked before it spreads a cloud

One clock: every time here is on the scan clock; an odometry stamp t_k becomes t_k +
odom_time_offset once, in the timeline. A scan's time t_s is ``scan.scan_time`` (the middle of its
sweep when it is timed); the pipeline runs it once the odometry reaches t_s, and its corrected
estimate x̂(t_s) becomes the timeline's anchor.

On each odometry message the pose at its time, x̂ ⊕ Δ(t_s, t'_k), is returned (what the node
publishes on /pf/pose/odom and TF); each sensor-corrected x̂(t_s) is collected for
``take_corrections`` (what the node publishes on /pf/pose when it is newer than the last one there).
Both go forward in time: t'_k grows, and t_s grows because scans are used in order.

Thread safety: two locks. The localizer's lock is held by a sensor update (and every other change of the
filter); the timeline has its own short one (``timeline.OdometryTimeline.lock``), held for one read or
write of the odometry history and the anchor. Odometry that arrives while the localizer's lock is held
goes into the timeline under the short lock alone, and the pose returned is the anchor (the last
corrected estimate) carried through the whole history to its time: odometry never waits for a sensor
update. Only a message that starts a new history (the first, or after a clock jump: the filter's times
move with it) waits for the localizer's lock.
"""
from __future__ import annotations

import enum
import logging
import math
import threading
from collections import deque
from dataclasses import dataclass

import numpy as np

from localization.core.compile_cache import ensure_compiled
from localization.core.cost import UpdateCost
from localization.core.filter.kld import KLDSampler
from localization.core.filter.mcl import MonteCarloLocalizer
from localization.core.localizer.initial_pose import check_initial_pose, waits_for_map
from localization.core.localizer.pipeline import ScanPipeline, Used
from localization.core.localizer.policies import ScanQueue
from localization.core.localizer.reconfigure import apply_change, prepare_change
from localization.core.localizer.recovery import Action
from localization.core.localizer.timeline import OdometryLimits, OdometryTimeline, Outbox, PoseEstimate
from localization.core.models.beam import BeamModel, BeamModelParams
from localization.core.models.likelihood_field import LikelihoodFieldModel, LikelihoodFieldParams
from localization.core.models.motion import MotionModel, MotionNoiseParams
from localization.core.models.sensor import SensorModel
from localization.core.occupancy_map import MapError, OccupancyMap
from localization.core.odometry import TwistData
from localization.core.parameters import Parameters
from localization.core.scan import ScanData, scan_time
from localization.core.throttled_log import ThrottledLog

__all__ = ["Ignored", "Localizer", "PoseEstimate", "ScanResult", "build_filter", "build_sensor_model"]

def build_sensor_model(params: Parameters) -> SensorModel:
    """The sensor model the ``sensor_model`` parameter names, configured from parameters."""
    if params.sensor_model == "likelihood_field":
        return LikelihoodFieldModel(LikelihoodFieldParams.from_parameters(params))
    return BeamModel(BeamModelParams.from_parameters(params))


def build_filter(params: Parameters, rng=None, sensor: SensorModel | None = None) -> MonteCarloLocalizer:
    """The particle filter and its models, configured from parameters (the table's names); ``sensor``:
    the sensor model to use (None: ``build_sensor_model``)."""
    rng = rng if rng is not None else np.random.default_rng(None if params.random_seed < 0 else params.random_seed)
    motion = MotionModel(params.deterministic, rng, MotionNoiseParams.from_parameters(params))
    sensor = build_sensor_model(params) if sensor is None else sensor
    kld = KLDSampler.from_parameters(params) if params.adaptive_particles else None
    return MonteCarloLocalizer(motion, sensor, params.num_particles, params.resample_ess_fraction,
                               (params.roughening_xy, params.roughening_xy, params.roughening_theta), rng, kld)


class Ignored(str, enum.Enum):
    """Why ``on_scan`` did not take a scan (compares equal to its value)."""

    UNUSABLE = "unusable"  # no ranges, or a non-finite stamp or angle
    NOT_READY = "not ready"  # no map, or no initial pose
    MAP_PENDING = "map pending"  # no map yet: the sensor model is preparing one
    STALE = "stale"  # stamped long before the latest odometry (a clock jump or a stale message)


@dataclass(frozen=True)
class ScanResult:
    """What ``on_scan`` did with a scan: ignored (why), or taken; the scans the call used (this one once the
    odometry covers its time, and any that waited for odometry), oldest first."""

    ignored: Ignored | None = None
    used: tuple[Used, ...] = ()

    @property
    def estimate(self) -> PoseEstimate | None:
        """The newest sensor-corrected estimate the call made (None: none)."""
        return next((u.estimate for u in reversed(self.used) if u.estimate is not None), None)

    @property
    def cost(self) -> UpdateCost | None:
        """What the newest scan the call used cost the core (``core.cost``; None: none used)."""
        return self.used[-1].cost if self.used else None


def scan_problem(scan: ScanData) -> tuple[str, str]:
    """(key, message) of what makes a scan unusable; ("", "") when it is usable."""
    if np.size(scan.ranges) == 0:
        return "scan-empty", "scan with no ranges ignored"
    if not all(math.isfinite(v) for v in (scan.stamp, scan.angle_min, scan.angle_max)):
        return "scan-angles", (f"scan with non-finite stamp or angles ignored (t={scan.stamp}, "
                               f"angle_min={scan.angle_min}, angle_max={scan.angle_max})")
    return "", ""


def waiting(loc: "Localizer", what: str) -> str:
    """Why ``what`` (an input) produced no pose: what the localizer waits for."""
    if loc.map_pending:
        return f"{what}: waiting for the sensor model to prepare the map (range table being built or loaded)"
    return f"{what}: " + ("no map received yet" if loc.map is None else
                          "waiting for an initial pose (/initialpose) or global localization")


class Localizer:
    def __init__(self, params: Parameters | None = None, logger: logging.Logger | None = None):
        self.params = p = params if params is not None else Parameters()
        self.log = logger or logging.getLogger("localization")
        self.warn = ThrottledLog(self.log)
        self._lock = threading.Lock()
        self._inbox: deque[TwistData] = deque()  # odometry not yet in the timeline (lock-free append)
        self._model = build_sensor_model(p)  # shared with the filter, the seeder and the challenger
        self._pf = build_filter(p, sensor=self._model)
        self._timeline = OdometryTimeline(OdometryLimits.from_parameters(p))
        self._queue = ScanQueue(p.scan_max_wait, p.scan_queue_size)
        self._pipeline = ScanPipeline(p, self._pf, self._model, self._timeline, self.warn, self.log)
        self.map: OccupancyMap | None = None
        self.map_pending = False  # a map's sensor-model preparation is under way elsewhere
        self._held_pose = None  # (pose, covariance, stamp): an initial pose waiting for the map on its way
        self._corrections = Outbox()  # sensor-corrected estimates not yet taken (its own lock)
        self.take_corrections = self._corrections.take  # those since the last call, oldest first
        self._costs = Outbox()  # the cost of each scan through the pipeline (``core.cost``), not yet taken
        self.take_costs = self._costs.take  # those since the last call, oldest first (UpdateCost each)

    has_map = property(lambda self: self.map is not None)
    ready = property(lambda self: self.map is not None and self._pf.initialized)
    health = property(lambda self: self._pipeline.recovery.health, doc="scan-map agreement, fast average (NaN: none)")
    status = property(lambda self: self._pipeline.recovery.status, doc="tracking, or: scans disagree with the map")
    num_particles = property(lambda self: self._pf.num_particles)
    global_mode = property(lambda self: self._pf.kld_hold, doc="a global spread, not yet converged")
    laser_offset = property(lambda self: np.array(self._model.laser_offset, dtype=float))
    waiting_scans = property(lambda self: len(self._queue), doc="scans waiting for odometry to reach them")
    recoveries = property(lambda self: self._pipeline.recoveries, doc="switches to a challenger and re-spreads")

    beams_used = property(lambda self: self._pf.beams_used,
                          doc="(used, offered) beams of the last sensor update (beam skipping leaves some out); None")

    refused_jumps = property(lambda self: self._pipeline.refused_jumps,
                             doc="sensor updates undone: they jumped to a place the scan fits no clearly better")

    range_scale_online = property(lambda self: self._pipeline.range_scale is not None,
                                  doc="the range scale is learnt while tracking (range_scale_estimation, beam model)")

    @property
    def range_scale(self) -> float:
        """The lidar-to-map range scale in use: the online estimate (``range_scale_estimation``), else
        ``lidar_scale_to_map_scale``."""
        learnt = self._pipeline.range_scale
        return self.params.lidar_scale_to_map_scale if learnt is None else learnt.scale

    def particles(self) -> np.ndarray:  # a copy (N, 3)
        with self._lock:
            return np.array(self._pf.particles, dtype=float)

    def estimate_at(self, t: float | None = None) -> PoseEstimate | None:
        """The latest corrected estimate carried to time t (scan clock; None: the newest odometry's)."""
        with self._lock:
            t = self._timeline.latest if t is None else t
            return self._timeline.anchor if t is None else self._timeline.pose_at(t)

    estimate = property(estimate_at)

    def scan_time(self, scan: ScanData) -> float:  # on the scan clock, under the scan_stamp convention
        return scan_time(scan, self.params.scan_stamp, self.params.scan_stamp_offset)

    def begin_map_preparation(self, pending: bool = True) -> None:  # False: preparing it failed
        self.map_pending = pending  # a map is being prepared elsewhere: inputs wait for it
        if not pending:
            self._apply_held_pose()

    def map_preparation(self, occupancy_map: OccupancyMap):  # slow? and a note for the log
        return self._model.preparation(occupancy_map)

    def prepare_ray_caster(self, occupancy_map: OccupancyMap):
        """The slow part of ``set_map`` (the sensor model's ``prepare``), safe on another thread."""
        self.map_pending = True
        ensure_compiled(self.params, self.log)
        return self._model.prepare(occupancy_map)

    def set_map(self, occupancy_map: OccupancyMap, prepared=None) -> None:
        """Use a (new) map; particles are kept if some stay in free space. No free space: MapError."""
        if len(occupancy_map.free_cells) == 0:
            raise MapError("map has no free cell (all unknown or occupied): ignored")
        if prepared is None:
            ensure_compiled(self.params, self.log)
        with self._lock:
            self._model.set_map(occupancy_map, prepared)
            self.map, self.map_pending = occupancy_map, False
            self._pipeline.set_map(occupancy_map)
            if self._pf.initialized and occupancy_map.is_occupied_or_outside(self._pf.particles[:, :2]).all():
                self.log.warning("new map: no particle lies in free space any more; waiting for a new initial pose")
                self._pf.forget()
                self._timeline.set_anchor(None)
            elif not self._pf.initialized and self.params.global_localization:
                self._spread_locked(self._timeline.latest)
        self._apply_held_pose()

    def set_laser_offset(self, offset) -> None:
        """The laser pose (x, y, yaw) in the robot frame, e.g. read from TF."""
        offset = np.asarray(offset, dtype=float).reshape(3)
        with self._lock:
            self._pipeline.set_laser_offset(offset)

    def request_update(self) -> None:
        """The next scan updates the filter even without motion (nav2's request_nomotion_update)."""
        with self._lock:
            self._pipeline.policy.force()

    def prepare_change(self, change):
        """The slow part of a runtime parameter change (``core.runtime_parameters``), safe on any thread."""
        return prepare_change(change, self.map, self.log)

    def reconfigure(self, change, prepared=None) -> None:
        """Apply a checked runtime parameter change between two updates (``core.localizer.reconfigure``);
        ``prepared``: what ``prepare_change`` made for it."""
        with self._lock:
            apply_change(change, self.params, self._pf, self._model, self.map, prepared)

    def set_initial_pose(self, pose, covariance=None, stamp: float = 0.0) -> bool:
        """(Re-)initialise the cloud around a pose (``core.localizer.initial_pose`` checks it); False: refused.
        Before a map, or while a new one is being prepared, the pose is kept and applied on that map."""
        wait = waits_for_map(pose, self.map, self.map_pending)
        if wait:
            self._held_pose = (pose, covariance, stamp)
            self.log.info(f"initial pose kept {wait}")
            return True
        init = check_initial_pose(pose, covariance, self.map, self.params, self.log)
        if init is None:
            return False
        with self._lock:
            self._pipeline.initialize(init, stamp)
            self._queue.clear()
        return True

    def _apply_held_pose(self) -> None:
        held, self._held_pose = self._held_pose, None
        if held is not None:
            self.set_initial_pose(*held)

    def initialize_global(self, stamp: float | None = None) -> bool:
        """Spread the particles over the free space (needs a map)."""
        with self._lock:
            return self._spread_locked(self._timeline.latest if stamp is None else stamp)

    def _spread_locked(self, stamp: float | None) -> bool:
        if self.map is None:
            self.log.warning("global localization requested before a map arrived: will spread once it does")
            return False
        self._pipeline.spread(stamp)
        self._queue.clear()
        return True

    def on_odometry(self, twist: TwistData, run_scans: bool = True) -> PoseEstimate | None:
        """Add odometry; the corrected estimate carried to its time t'_k (``run_scans`` False: the scans
        it releases wait for ``run_waiting``, on a sensor-update thread)."""
        self._inbox.append(twist)
        if not self._lock.acquire(blocking=False):  # a sensor update runs: the timeline's short lock only
            taken, pose = self._odometry_during_update()
            if taken:
                return pose
            self._lock.acquire()  # a message that starts a history (rare: the first, a clock jump) waits
        try:
            accepted = self._add_odometry_locked()
            if run_scans:
                self._run_released_locked()
            if not self.ready:
                self.warn("odom-not-ready", waiting(self, "odometry kept; no pose yet"), logging.INFO)
            return self._timeline.pose_at(self._timeline.latest) if accepted and self.ready else None
        finally:
            self._lock.release()

    def _odometry_during_update(self) -> tuple[bool, PoseEstimate | None]:
        """While another call holds the localizer's lock: the odometry waiting in the inbox that continues the
        history goes into the timeline (its short lock). (True, the anchor carried to the newest one, or None
        before a pose), or (False, None) when a message the inbox still holds starts a new history (it needs
        the localizer's lock: the filter's times move with it)."""
        timeline = self._timeline
        with timeline.lock:
            while self._inbox and timeline.continues(self._inbox[0]):
                timeline.add(self._inbox.popleft())
            if self._inbox:
                return False, None
            return True, (timeline.pose_at(timeline.latest) if self.ready else None)

    @property
    def scans_due(self) -> bool:
        """Scans wait that the odometry received reaches (``on_odometry(run_scans=False)`` left them for
        ``run_waiting``); a hint read without the localizer's lock."""
        latest = self._timeline.latest
        return latest is not None and self._queue.due(latest)

    def run_waiting(self) -> None:
        """Use the scans the odometry received so far has released (the sensor-update thread's call)."""
        with self._lock:
            self._add_odometry_locked()
            self._run_released_locked()

    def _add_odometry_locked(self) -> bool:
        """Odometry from the inbox into the timeline (under its short lock too: odometry may arrive on another
        thread meanwhile); was the last one accepted?"""
        accepted = False
        with self._timeline.lock:
            while self._inbox:
                verdict = self._timeline.add(self._inbox.popleft())
                accepted = verdict.accepted
                if not accepted:
                    self.warn(verdict.key, verdict.problem)
                elif verdict.restart is not None and self._pipeline.t_filter is not None:  # a new history: the
                    self._pipeline.restart_clock(verdict.restart)  # filter's times move to its start
            self._timeline.rebase_anchor()  # keep the history short
            self._timeline.trim(self._pipeline.t_filter)
        return accepted

    def _run_released_locked(self) -> tuple[Used, ...]:
        """Every scan the odometry now covers, oldest first, through the pipeline."""
        used = []
        for item in self._queue.release(None if self._timeline.empty else self._timeline.latest):
            if item.late:
                self.warn("scan-late", item.warning(self.params.scan_max_wait))
            used.append(self._run_locked(item.scan, item.time))
        return tuple(used)

    def on_scan(self, scan: ScanData) -> ScanResult:
        """Queue a scan until odometry reaches its time, and use every scan that may be used now; what
        happened to it (``ScanResult``: ignored and why, or the scans used and the newest estimate)."""
        key, problem = scan_problem(scan)
        if key:
            self.warn(key, problem)
            return ScanResult(Ignored.UNUSABLE)
        with self._lock:
            if not self.ready:
                self.warn("scan-not-ready", waiting(self, "scan ignored"), logging.INFO)
                return ScanResult(Ignored.MAP_PENDING if self.map_pending else Ignored.NOT_READY)
            latest = self._timeline.latest
            t_s = self.scan_time(scan) if self.params.align_odometry or latest is None else latest
            if latest is not None and t_s < latest - self.params.odom_max_gap:
                self.warn("scan-stale", f"scan stamped {latest - t_s:.2f} s before the latest odometry ignored "
                          "(a clock jump or a stale message)")
                return ScanResult(Ignored.STALE)
            self._queue.push(t_s, scan)
            self._add_odometry_locked()
            return ScanResult(used=self._run_released_locked())

    def flush(self) -> None:
        """Use every waiting scan now, the last twist extrapolated (the end of a recording)."""
        with self._lock:
            for item in self._queue.release(None):
                self._run_locked(item.scan, item.time)

    def _run_locked(self, scan: ScanData, t_s: float) -> Used:
        """One scan through the pipeline; its corrected estimate is collected for ``take_corrections``."""
        used = self._pipeline.run(scan, t_s)
        self._costs.put(used.cost)
        if used.action is Action.RESPREAD:  # the scans waiting describe the cloud before it
            self._queue.clear()
        if used.estimate is not None:
            self._corrections.put(used.estimate)
        return used
