"""The localizer: one orchestrator, shared by the node, replay, the tuner and the benchmarks.

It turns a stream of odometry twists and scans into pose estimates, by handing each input to the
small part whose one job it is:

    OdometryTimeline (timeline)   odometry on the scan clock; the pose at any time (anchor ⊕ Δ)
    ScanQueue (policies)          a scan waits for the odometry that covers its time
    UpdatePolicy (policies)       does this scan update the filter (forced/moved/turned/stopped/every n)
    MonteCarloLocalizer (filter)  motion update to the scan's time, sensor update, resampling
    GlobalSeeder                  where a global spread puts its particles
    RecoveryPolicy (recovery)     converged / tracking / lost, after each sensor update

One clock: every time here is on the scan clock; an odometry stamp t_k becomes t_k +
odom_time_offset once, in the timeline. A scan's time t_s is ``scan.scan_time`` (the middle of its
sweep when it is timed). Per scan, once the odometry reaches t_s:

    particles ← particles ⊕ (Δ pieces from t_filter to t_s, with motion noise)      t_filter ← t_s
    if the update policy says so: sensor update with the beams cast from the laser pose at each
    beam's own time (deskew), resample, x̂(t_s) = weighted mean → the timeline's anchor

On each odometry message the pose at its time, x̂ ⊕ Δ(t_s, t'_k), is returned (what the node
publishes on /pf/pose/odom and TF); each sensor-corrected x̂(t_s) is collected for
``take_corrections`` (what the node publishes on /pf/pose when it is newer than the last one there).
Both go forward in time: t'_k grows, and t_s grows because scans are used in order.

Thread safety: one lock. Odometry that arrives while a sensor update holds it goes into an inbox
(lock-free) and is added by the next call that holds the lock; meanwhile the pose returned is the
last one carried on by the new twist alone, so odometry never waits for a slow scan.
"""
from __future__ import annotations

import logging
import math
import threading
from collections import deque

import numpy as np

from localization.core.compile_cache import ensure_compiled
from localization.core.filter.kld import KLDSampler
from localization.core.filter.mcl import MonteCarloLocalizer
from localization.core.geometry import compose, integrate_twist, integrate_twists, inverse
from localization.core.global_seeder import GlobalSeeder
from localization.core.motion import MotionModel, MotionNoiseParams
from localization.core.occupancy_map import MapError, OccupancyMap
from localization.core.odometry import TwistData
from localization.core.parameters import Parameters
from localization.core.policies import ScanQueue, UpdatePolicy, UpdatePolicyParams
from localization.core.recovery import RecoveryPolicy
from localization.core.scan import ScanData, downsample_scan, scan_time, sweep_increment
from localization.core.sensors.beam import BeamModel, BeamModelParams
from localization.core.sensors.likelihood_field import LikelihoodFieldModel, LikelihoodFieldParams
from localization.core.throttled_log import ThrottledLog
from localization.core.timeline import OdometryLimits, OdometryTimeline, PoseEstimate

__all__ = ["Localizer", "PoseEstimate", "build_filter", "usable_covariance"]

MAX_INITIAL_VARIANCE = 1.0e4  # m², rad²: an initial-pose covariance entry beyond this is not a pose estimate


def build_filter(params: Parameters, rng=None) -> MonteCarloLocalizer:
    """The particle filter and its models, configured from parameters (the table's names)."""
    rng = rng if rng is not None else np.random.default_rng(None if params.random_seed < 0 else params.random_seed)
    motion = MotionModel(params.deterministic, rng, MotionNoiseParams.from_parameters(params))
    if params.sensor_model == "likelihood_field":
        sensor = LikelihoodFieldModel(LikelihoodFieldParams.from_parameters(params))
    else:
        sensor = BeamModel(BeamModelParams.from_parameters(params))
    kld = KLDSampler.from_parameters(params) if params.adaptive_particles else None
    return MonteCarloLocalizer(motion, sensor, params.num_particles, params.resample_ess_fraction,
                               (params.roughening_xy, params.roughening_xy, params.roughening_theta), rng, kld)


def usable_covariance(cov) -> bool:
    """A 3×3 initial-pose covariance that can spread a cloud (finite, not zero, not absurd)."""
    return bool(np.all(np.isfinite(cov)) and np.trace(cov) > 0 and np.abs(cov).max() <= MAX_INITIAL_VARIANCE)


def scan_problem(scan: ScanData) -> tuple[str, str]:
    """(key, message) of what makes a scan unusable; ("", "") when it is usable."""
    if np.size(scan.ranges) == 0:
        return "scan-empty", "scan with no ranges ignored"
    if not all(math.isfinite(v) for v in (scan.stamp, scan.angle_min, scan.angle_max)):
        return "scan-angles", (f"scan with non-finite stamp or angles ignored (t={scan.stamp}, "
                               f"angle_min={scan.angle_min}, angle_max={scan.angle_max})")
    return "", ""


class Localizer:
    def __init__(self, params: Parameters | None = None, logger: logging.Logger | None = None):
        self.params = p = params if params is not None else Parameters()
        self.log = logger or logging.getLogger("localization")
        self.warn = ThrottledLog(self.log)
        self._lock = threading.Lock()
        self._inbox: deque[TwistData] = deque()  # odometry not yet in the timeline (lock-free append)
        self._pf = build_filter(p)
        self._timeline = OdometryTimeline(OdometryLimits.from_parameters(p))
        self._queue = ScanQueue(p.scan_max_wait, p.scan_queue_size)
        self._policy = UpdatePolicy(UpdatePolicyParams.from_parameters(p))
        self._seeder = GlobalSeeder(p, self.log)
        self._recovery = RecoveryPolicy(p)
        self.map: OccupancyMap | None = None
        self.map_pending = False  # a map's sensor-model preparation is under way elsewhere
        self._t_filter: float | None = None  # s, scan clock: the time the particles describe
        self._t_update: float | None = None  # s, scan clock: the last sensor update
        self._corrections: list[PoseEstimate] = []
        self._carried: PoseEstimate | None = None  # the last pose returned on odometry
        self._impossible = 0
        self.recoveries = 0

    # ------------------------------------------------------------------ state (read by the node)
    has_map = property(lambda self: self.map is not None)
    ready = property(lambda self: self.map is not None and self._pf.initialized)
    health = property(lambda self: self._recovery.health, doc="scan-map agreement, fast average (NaN: none)")
    num_particles = property(lambda self: self._pf.num_particles)
    global_mode = property(lambda self: self._pf.kld_hold, doc="a global spread, not yet converged")
    global_particle_count = property(lambda self: self._seeder.count)
    laser_offset = property(lambda self: np.array(self._pf.sensor_model.laser_offset, dtype=float))
    waiting_scans = property(lambda self: len(self._queue), doc="scans waiting for odometry to reach them")

    def particles(self) -> np.ndarray:
        with self._lock:
            return np.array(self._pf.particles, dtype=float)

    @property
    def estimate(self) -> PoseEstimate | None:
        """The latest corrected estimate carried to the newest odometry's time (scan clock)."""
        with self._lock:
            latest = self._timeline.latest
            return self._timeline.anchor if latest is None else self._timeline.pose_at(latest)

    def estimate_at(self, t: float) -> PoseEstimate | None:
        """The latest corrected estimate carried through the odometry to time t (scan clock)."""
        with self._lock:
            return self._timeline.pose_at(t)

    def scan_time(self, scan: ScanData) -> float:
        return scan_time(scan)

    def take_corrections(self) -> list[PoseEstimate]:
        """Sensor-corrected estimates since the last call, oldest first, each at its scan's time."""
        with self._lock:
            out, self._corrections = self._corrections, []
        return out

    # ------------------------------------------------------------------ map, laser, initialisation
    def begin_map_preparation(self) -> None:
        self.map_pending = True

    def cancel_map_preparation(self) -> None:
        self.map_pending = False

    def map_preparation(self, occupancy_map: OccupancyMap):
        """Whether preparing this map is slow (and a note for the log): the sensor model's answer."""
        return self._pf.sensor_model.preparation(occupancy_map)

    def prepare_ray_caster(self, occupancy_map: OccupancyMap):
        """The slow part of ``set_map`` (the sensor model's ``prepare``), safe on another thread."""
        self.map_pending = True
        ensure_compiled(self.params, self.log)
        return self._pf.sensor_model.prepare(occupancy_map)

    def set_map(self, occupancy_map: OccupancyMap, prepared=None) -> None:
        """Use a (new) map; particles are kept if some stay in free space. No free space: MapError."""
        if len(occupancy_map.free_cells) == 0:
            raise MapError("map has no free cell (all unknown or occupied): ignored")
        if prepared is None:
            ensure_compiled(self.params, self.log)
        with self._lock:
            self._pf.sensor_model.set_map(occupancy_map, prepared)
            self.map, self.map_pending = occupancy_map, False
            self._recovery.set_map(occupancy_map, self._pf.sensor_model.laser_offset)
            if self._pf.initialized and occupancy_map.is_occupied_or_outside(self._pf.particles[:, :2]).all():
                self.log.warning("new map: no particle lies in free space any more; waiting for a new initial pose")
                self._pf.initialized = False
                self._timeline.set_anchor(None)
            elif not self._pf.initialized and self.params.global_localization:
                self._spread_locked(self._timeline.latest)

    def set_laser_offset(self, offset) -> None:
        """The laser pose (x, y, yaw) in the robot frame, e.g. read from TF."""
        offset = np.asarray(offset, dtype=float).reshape(3)
        with self._lock:
            self._pf.sensor_model.set_laser_offset(offset)
            self._recovery.set_laser_offset(offset)

    def request_update(self) -> None:
        """The next scan updates the filter even without motion (nav2's request_nomotion_update)."""
        with self._lock:
            self._policy.force()

    def set_initial_pose(self, pose, covariance=None, stamp: float = 0.0) -> bool:
        """(Re-)initialise the cloud around a pose (covariance 3×3 over x, y, θ if given); a non-finite
        pose is refused, one off the map or in a wall is moved to the nearest free cell."""
        pose = np.asarray(pose, dtype=float).reshape(3)
        if not np.all(np.isfinite(pose)):
            self.log.warning(f"initial pose {pose.tolist()} is not finite: ignored")
            return False
        if self.map is not None and not self.map.is_free(pose[None, :2])[0]:
            nearest = self.map.nearest_free(pose[:2])
            self.log.warning(f"initial pose ({pose[0]:.2f}, {pose[1]:.2f}) is not in free space: "
                             f"moved to the nearest free cell ({nearest[0]:.2f}, {nearest[1]:.2f})")
            pose = np.array([nearest[0], nearest[1], pose[2]])
        cov = None
        if covariance is not None and self.params.use_initialpose_covariance:
            cov = np.asarray(covariance, dtype=float).reshape(3, 3)
            if not usable_covariance(cov):
                self.log.warning(f"initial pose covariance {np.diag(cov).tolist()} (diagonal) is not a usable spread "
                                 "(non-finite, zero, or beyond 1e4): using initial_std_xy / initial_std_theta")
                cov = None
        p = self.params
        with self._lock:
            self._pf.resize(p.num_particles)
            self._pf.kld_hold = False
            self._pf.initialize_gaussian(pose, cov, (p.initial_std_xy, p.initial_std_xy, p.initial_std_theta))
            self._after_init_locked(stamp)
        return True

    def initialize_global(self, stamp: float | None = None) -> bool:
        """Spread the particles over the free space (needs a map)."""
        with self._lock:
            return self._spread_locked(self._timeline.latest if stamp is None else stamp)

    def _spread_locked(self, stamp: float | None) -> bool:
        if self.map is None:
            self.log.warning("global localization requested before a map arrived: will spread once it does")
            return False
        self._seeder.spread(self._pf, self.map)
        self._after_init_locked(stamp)
        return True

    def _after_init_locked(self, stamp: float | None) -> None:
        """The particles describe ``stamp`` (scan clock; the newest odometry's time if unusable)."""
        self._recovery.restart()
        self._policy.force()
        self._queue.clear()
        self._t_filter = self._t_update = self._timeline.usable(stamp) if not self._timeline.empty else stamp
        est = self._pf.estimate()
        t = self._t_filter if self._t_filter is not None and math.isfinite(self._t_filter) else 0.0
        self._timeline.set_anchor(PoseEstimate(stamp=t, pose=est.pose, covariance=est.covariance))

    # ------------------------------------------------------------------ odometry
    def on_odometry(self, twist: TwistData) -> PoseEstimate | None:
        """Add an odometry message; returns the latest corrected estimate carried to its time t'_k."""
        self._inbox.append(twist)
        if not self._lock.acquire(blocking=False):  # a sensor update runs: carry the last pose by this twist
            return self._carry_unlocked(twist)
        try:
            accepted = self._drain_locked()
            pose = self._timeline.pose_at(self._timeline.latest) if accepted and self.ready else None
            if not self.ready:
                self.warn("odom-not-ready", self._not_ready_reason("odometry kept; no pose yet"), logging.INFO)
            self._carried = pose
            return pose
        finally:
            self._lock.release()

    def _carry_unlocked(self, twist: TwistData) -> PoseEstimate | None:
        last, lim = self._carried, self._timeline.limits
        t = twist.stamp + lim.time_offset
        if last is None or not t > last.stamp or t - last.stamp > lim.max_gap:
            return last
        delta = integrate_twist(lim.speed_scale * twist.vx, lim.speed_scale * twist.vy,
                                lim.yaw_rate_scale * twist.wz + lim.yaw_rate_bias, t - last.stamp)
        self._carried = PoseEstimate(stamp=t, pose=compose(last.pose, delta), covariance=last.covariance)
        return self._carried

    def _drain_locked(self) -> bool:
        """Odometry from the inbox into the timeline, then every scan that may now be used; returns
        whether the last odometry message was accepted."""
        accepted = False
        while self._inbox:
            verdict = self._timeline.add(self._inbox.popleft())
            accepted = verdict.accepted
            if not accepted:
                self.warn(verdict.key, verdict.problem)
            elif verdict.restart is not None and self._t_filter is not None:  # a new history: the filter's
                self._t_filter = self._t_update = verdict.restart  # times move to its start
        anchor, latest = self._timeline.anchor, self._timeline.latest
        if anchor is not None and latest is not None and anchor.stamp < latest - 0.5 * self.params.odom_max_gap:
            self._timeline.set_anchor(self._timeline.pose_at(latest))  # keep the history short
        for item in self._queue.release(None if self._timeline.empty else self._timeline.latest):
            if item.late:
                self.warn("scan-late", f"no odometry reached a scan's time after {item.waited:.2f} s (scan_max_wait "
                          f"{self.params.scan_max_wait} s): the last twist is extrapolated. Odometry is late or "
                          "stopped: check odom_time_offset, or raise scan_max_wait")
            self._update_locked(item.scan, item.time)
        return accepted

    # ------------------------------------------------------------------ scans
    def on_scan(self, scan: ScanData) -> PoseEstimate | None:
        """Queue a scan until odometry reaches its time, and use every scan that may be used now;
        returns the newest sensor-corrected estimate made by this call (None: none)."""
        key, problem = scan_problem(scan)
        if key:
            self.warn(key, problem)
            return None
        with self._lock:
            if not self.ready:
                self.warn("scan-not-ready", self._not_ready_reason("scan ignored"), logging.INFO)
                return None
            latest = self._timeline.latest
            t_s = scan_time(scan) if self.params.align_odometry or latest is None else latest
            if latest is not None and t_s < latest - self.params.odom_max_gap:
                self.warn("scan-stale", f"scan stamped {latest - t_s:.2f} s before the latest odometry ignored "
                          "(a clock jump or a stale message; odometry going back resets the reference)")
                return None
            before = len(self._corrections)
            self._queue.push(t_s, scan)
            self._drain_locked()
            return self._corrections[-1] if len(self._corrections) > before else None

    def _move_particles_locked(self, t: float) -> None:
        """Particles to time t through the odometry (noise per piece; exactly back if t is older)."""
        t_from = self._timeline.usable(self._t_filter)
        if t_from is None or self._timeline.empty:
            self._t_filter = t
            return
        if t < t_from:
            self._pf.shift(inverse(self._timeline.motion(t, t_from)))
        dts, twists = self._timeline.segments(t_from, t)
        for delta in integrate_twists(twists[:, 0], twists[:, 1], twists[:, 2], dts):
            self._pf.motion_update(delta)
        self._t_filter = t

    def _update_locked(self, scan: ScanData, t_s: float) -> None:
        """One scan at its time t_s: motion to t_s, and a sensor update when the policy says so."""
        p = self.params
        self._move_particles_locked(t_s)
        t_last = self._timeline.usable(self._t_update)
        distance, angle = self._timeline.travel(t_s if t_last is None else t_last, t_s)
        vx, vy, wz = self._timeline.twist_at(t_s)
        if self._policy.reason(distance, angle, math.hypot(vx, vy), wz) is None:
            return
        rmin, rmax = scan.range_min, scan.range_max
        if not (math.isfinite(rmin) and math.isfinite(rmax) and 0 <= rmin < rmax):
            self.warn("scan-limits", f"scan range limits [{rmin}, {rmax}] are unusable: using [0, "
                      f"{self._pf.sensor_model.max_range:.2f}] m")
            rmin, rmax = 0.0, self._pf.sensor_model.max_range
        beams = downsample_scan(scan, p.num_beams_per_particle, rmin, rmax)
        if not np.isfinite(beams.ranges).any():
            self.warn("scan-invalid", "scan with no valid range (all NaN, inf or out of limits) ignored")
            return
        self._seeder.seed(self._pf, self.map, beams.ranges, beams.angles)
        result = self._pf.sensor_update(beams.ranges, beams.angles, self._deskew(scan, t_s, beams.indices),
                                        range_max=rmax)
        if not result.ok:
            self._impossible += 1
            if self._impossible < p.max_impossible_scans:
                self.warn("scan-degenerate", "every particle has likelihood 0 for this scan: weights kept")
                return
            self.log.warning(f"{self._impossible} scans in a row gave every particle likelihood 0 (all off the map "
                             "or in walls): re-spreading particles over the free space")
            self._impossible, self.recoveries = 0, self.recoveries + 1
            self._spread_locked(t_s)
            return
        self._impossible, self._t_update = 0, t_s
        self._policy.updated(math.hypot(vx, vy), wz)
        est = self._pf.estimate()
        verdict = self._recovery.judge(est.pose, est.covariance, beams.ranges, beams.angles, rmin, rmax,
                                       self.global_mode)
        if verdict.converged:
            self._pf.kld_hold = False
            if self._pf.kld is None:
                self._pf.resize(p.num_particles)
            self.log.info(f"global localization converged at ({est.pose[0]:.2f}, {est.pose[1]:.2f}, "
                          f"{est.pose[2]:.2f}): {self._pf.num_particles} particles")
        if verdict.lost:
            self.log.warning(verdict.message)
            self.recoveries += 1
            self._spread_locked(t_s)
            est = self._pf.estimate()
        corrected = PoseEstimate(stamp=t_s, pose=est.pose, covariance=est.covariance)
        self._timeline.set_anchor(corrected)
        self._corrections.append(corrected)

    def _deskew(self, scan: ScanData, t_s: float, idx):
        """Per-beam laser motion δ_b = L⁻¹ ⊕ Δ_b ⊕ L (B, 3) from t_s to each beam's own time, Δ_b the
        robot's arc under the twist at t_s, L the laser pose; None without sweep timing."""
        sweep = sweep_increment(scan)
        if not (sweep > 0 and self.params.deskew and self._pf.sensor_model.supports_deskew):
            return None
        vx, vy, wz = self._timeline.twist_at(t_s)
        robot = integrate_twists(vx, vy, wz, scan.stamp + idx * sweep - t_s)
        laser = np.asarray(self._pf.sensor_model.laser_offset, dtype=float)
        return compose(inverse(laser), compose(robot, laser))

    def _not_ready_reason(self, what: str) -> str:
        if self.map_pending:
            return f"{what}: waiting for the sensor model to prepare the map (range table being built or loaded)"
        if self.map is None:
            return f"{what}: no map received yet"
        return f"{what}: waiting for an initial pose (/initialpose) or global localization"
