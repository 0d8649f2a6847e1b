"""The localizer: what to do with each incoming message, shared by the node and the replay tool.

It owns the map, the models and the particle filter, and turns a stream of
(odometry twist, stamp) and (scan, stamp) into pose estimates:

- odometry: dt from consecutive *message stamps* (never the wall clock), so bags replay right at
  any rate; the twist (vx, vy, ωz) is integrated over dt along a constant-twist arc and applied
  to every particle. A stamp going backwards or a gap longer than ``max_odom_gap`` resets the
  reference instead of moving particles;
- scan: downsampled, then a sensor update (+ resampling) once the car has moved
  ``update_min_distance`` / ``update_min_angle`` since the last one (always right after an
  initialisation, so a parked car's cloud still tightens once);
- nothing happens before a map and an initial pose (or a global initialisation) have arrived;
- health and recovery (``localization.health``): after each sensor update of a converged cloud the
  estimate is scored against the scan (``health``); a lost filter is re-spread over the free space
  with ``global_num_particles``, which shrink back to ``num_particles`` once the cloud converges.

Thread safety: the node may call ``on_odometry`` while ``on_scan`` runs. Odometry that arrives
during a sensor update is queued and applied before the next update, and the returned estimate
is the last one composed with the queued motion, so odometry never waits for a slow scan.
"""
from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass

import numpy as np

from localization.core.filter.mcl import Estimate, MonteCarloLocalizer
from localization.core.geometry import compose, integrate_twist
from localization.core.health import AgreementScorer, HealthMonitor, cloud_spread
from localization.core.motion import MotionModel, MotionNoiseParams
from localization.core.occupancy_map import MapError, OccupancyMap
from localization.core.odometry import TwistData
from localization.core.parameters import Parameters
from localization.core.scan import ScanData, downsample_scan
from localization.core.sensors.beam import BeamModel, BeamModelParams


@dataclass
class PoseEstimate:
    stamp: float  # seconds: the time of the data the estimate reflects
    pose: np.ndarray  # (3,)
    covariance: np.ndarray  # (3, 3)


def build_filter(params: Parameters, rng=None) -> MonteCarloLocalizer:
    """The particle filter and its models, configured from parameters (the table's names)."""
    rng = rng if rng is not None else np.random.default_rng(None if params.random_seed < 0 else params.random_seed)
    motion = MotionModel(params.deterministic, rng, MotionNoiseParams.from_parameters(params))
    sensor = BeamModel(BeamModelParams.from_parameters(params))
    return MonteCarloLocalizer(motion, sensor, params.num_particles, params.resample_ess_fraction,
                               (params.roughening_xy, params.roughening_xy, params.roughening_theta), rng)


class ThrottledLog:
    """Log each kind of message at most once per ``period`` seconds (wall clock), counting the
    repeats, so a broken sensor at 40 Hz gives one clear line, not a flood."""

    def __init__(self, logger: logging.Logger, period: float = 5.0):
        self.logger, self.period = logger, period
        self._last: dict[str, tuple[float, int]] = {}

    def __call__(self, key: str, message: str, level: int = logging.WARNING) -> None:
        now = time.monotonic()
        last, repeats = self._last.get(key, (-np.inf, 0))
        if now - last >= self.period:
            suffix = f" ({repeats} more since the last report)" if repeats else ""
            self.logger.log(level, message + suffix)
            self._last[key] = (now, 0)
        else:
            self._last[key] = (last, repeats + 1)


class Localizer:
    def __init__(self, params: Parameters | None = None, logger: logging.Logger | None = None):
        self.params = params if params is not None else Parameters()
        self.log = logger or logging.getLogger("localization")
        self.warn = ThrottledLog(self.log)
        self.filter = build_filter(self.params)
        self.map: OccupancyMap | None = None
        self._lock = threading.Lock()
        self._pending = np.zeros(3)  # odometry received during a sensor update
        self._pending_stamp = -math.inf
        self._pending_lock = threading.Lock()
        self._last_odom_stamp: float | None = None
        self._odom_before_jump: float | None = None  # the reference before a stamp jump (one bad stamp?)
        self._since_update = np.zeros(2)  # distance, angle travelled since the last sensor update
        self._force_update = False
        self._estimate: PoseEstimate | None = None
        self._impossible_scans = 0
        self.health_monitor = HealthMonitor.from_params(self.params)
        self._scorer: AgreementScorer | None = None
        self.global_mode = False  # particles spread globally (start, service or recovery), not yet converged
        self.recoveries = 0  # re-spreads after the filter was judged lost (or every particle impossible)

    # ------------------------------------------------------------------ state
    @property
    def has_map(self) -> bool:
        return self.map is not None

    @property
    def ready(self) -> bool:
        return self.map is not None and self.filter.initialized

    @property
    def health(self) -> float:
        """Scan-map agreement of the estimate, fast average in [0, 1] (see localization.health);
        NaN before the first sensor update of a converged cloud."""
        return self.health_monitor.health

    @property
    def estimate(self) -> PoseEstimate | None:
        """The latest estimate, including odometry queued during a running sensor update."""
        est = self._estimate
        if est is None:
            return None
        with self._pending_lock:
            pending, pending_stamp = self._pending.copy(), self._pending_stamp
        if pending.any():
            return PoseEstimate(max(est.stamp, pending_stamp), compose(est.pose, pending), est.covariance)
        return est

    # ------------------------------------------------------------------ inputs
    def set_map(self, occupancy_map: OccupancyMap) -> None:
        """Use a (new) map. Particles are kept if they stay valid, else re-initialised.
        A map without free space raises MapError and the previous map stays in use."""
        if len(occupancy_map.free_cells) == 0:
            raise MapError("map has no free cell (all unknown or occupied): ignored")
        with self._lock:
            self.filter.sensor_model.set_map(occupancy_map)
            self.map = occupancy_map
            self._scorer = AgreementScorer(occupancy_map, self.filter.sensor_model.laser_offset)
            self.health_monitor.reset()
            if self.filter.initialized:
                inside = ~occupancy_map.is_occupied_or_outside(self.filter.particles[:, :2])
                if not inside.any():
                    self.log.warning("new map: no particle lies in free space any more; waiting for a new initial pose")
                    self.filter.initialized = False
                    self._estimate = None
            elif self.params.global_localization:
                self._initialize_global_locked()

    def set_initial_pose(self, pose, covariance=None, stamp: float = 0.0) -> bool:
        """(Re-)initialise the cloud around a pose; covariance (3×3 over x, y, θ) if given.

        Returns False (and logs why) for a non-finite pose. A pose off the map or inside a wall is
        moved to the nearest free cell, with a warning."""
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
            if not (np.all(np.isfinite(cov)) and np.trace(cov) > 0):
                cov = None
        std = (self.params.initial_std_xy, self.params.initial_std_xy, self.params.initial_std_theta)
        with self._lock:
            self.filter.resize(self.params.num_particles)
            self.global_mode = False
            self.filter.initialize_gaussian(pose, cov, std)
            self._after_init(stamp)
        return True

    def initialize_global(self, stamp: float = 0.0) -> bool:
        """Spread particles uniformly over the free space (needs a map)."""
        with self._lock:
            return self._initialize_global_locked(stamp)

    def _initialize_global_locked(self, stamp: float = 0.0) -> bool:
        if self.map is None:
            self.log.warning("global localization requested before a map arrived: will spread once it does")
            return False
        self.filter.resize(self.params.global_num_particles)
        self.filter.initialize_uniform(self.map)
        self.global_mode = True
        self._after_init(stamp)
        return True

    def _after_init(self, stamp: float) -> None:
        self.health_monitor.reset(keep_slow=True)
        with self._pending_lock:
            self._pending[:] = 0.0
        self._force_update = True
        self._since_update[:] = 0.0
        est = self.filter.estimate()
        self._estimate = PoseEstimate(stamp, est.pose, est.covariance)

    def on_odometry(self, twist: TwistData) -> PoseEstimate | None:
        """Apply the motion since the previous odometry message; returns the new estimate."""
        stamp, vx, vy, wz = twist.stamp, twist.vx, twist.vy, twist.wz
        if not all(math.isfinite(v) for v in (stamp, vx, vy, wz)):
            self.warn("odom-nan", f"odometry with a non-finite value ignored (t={stamp}, v=({vx}, {vy}), w={wz})")
            return None
        if math.hypot(vx, vy) > self.params.odom_max_speed or abs(wz) > self.params.odom_max_yaw_rate:
            self.warn("odom-absurd", f"odometry with an absurd speed ignored (v=({vx:.1f}, {vy:.1f}) m/s, "
                      f"w={wz:.1f} rad/s; limits {self.params.odom_max_speed} m/s, "
                      f"{self.params.odom_max_yaw_rate} rad/s)")
            return None
        last, self._last_odom_stamp = self._last_odom_stamp, stamp
        if last is None or not self.ready:
            if not self.ready:
                self.warn("odom-not-ready", self._not_ready_reason("odometry"), logging.INFO)
            return None
        dt = stamp - last
        before_jump, self._odom_before_jump = self._odom_before_jump, None
        max_gap = self.params.odom_max_gap
        if not 0.0 < dt <= max_gap and before_jump is not None and 0.0 < stamp - before_jump <= max_gap:
            dt = stamp - before_jump  # the jump was one message with a bad stamp: continue from before it
        if dt <= 0.0 or dt > self.params.odom_max_gap:
            self._odom_before_jump = last
            self.warn("odom-jump", f"odometry stamp jumped by {dt:+.3f} s (bag loop or sensor restart): "
                      "motion reference reset, particles not moved")
            return None
        delta = integrate_twist(vx, vy, wz, dt)
        if self._lock.acquire(blocking=False):
            try:
                self._apply_motion(delta)
                est = self.filter.estimate()
                self._estimate = PoseEstimate(stamp, est.pose, est.covariance)
            finally:
                self._lock.release()
        else:  # a sensor update is running: queue the motion, predict from the last estimate
            with self._pending_lock:
                self._pending = compose(self._pending, delta)
                self._pending_stamp = stamp
        return self.estimate

    def _apply_motion(self, delta) -> None:
        with self._pending_lock:
            pending, self._pending = self._pending, np.zeros(3)
        if pending.any():
            delta = compose(pending, delta)
        self.filter.motion_update(delta)
        self._since_update += (np.hypot(delta[0], delta[1]), abs(delta[2]))

    def _check_health(self, est, scan, range_min: float, range_max: float, stamp: float):
        """After a sensor update (lock held): shrink a converged global cloud back to num_particles;
        score a converged estimate against the scan and re-spread globally when the filter is lost."""
        if self.global_mode:
            if cloud_spread(est.covariance) >= self.params.global_converged_std:
                return est  # still spread: the mean pose of many hypotheses says nothing yet
            self.global_mode = False
            self.filter.resize(self.params.num_particles)
            self.health_monitor.reset(keep_slow=True)
            self.log.info(f"global localization converged at ({est.pose[0]:.2f}, {est.pose[1]:.2f}, "
                          f"{est.pose[2]:.2f}): {self.params.num_particles} particles")
        agreement = self._scorer.score(est.pose, scan.ranges, scan.angles, range_min, range_max)
        if self.health_monitor.update(agreement) and self.params.recovery:
            m = self.health_monitor
            self.log.warning(f"localization lost: scan-map agreement {m.fast:.2f} (long-term {m.slow:.2f}) for "
                             f"{m.low_count} updates; re-spreading {self.params.global_num_particles} particles "
                             "over the free space (recovery)")
            self.recoveries += 1
            self._initialize_global_locked(stamp)
            est = self.filter.estimate()
        return est

    def _not_ready_reason(self, what: str) -> str:
        if self.map is None:
            return f"{what} ignored: no map received yet"
        return f"{what} ignored: waiting for an initial pose (/initialpose) or global localization"

    def on_scan(self, full_scan: ScanData) -> PoseEstimate | None:
        """Sensor update (+ resampling) from a full scan; returns the new estimate, or None
        when the filter is not ready or the car has not moved enough since the last update."""
        if not self.ready:
            self.warn("scan-not-ready", self._not_ready_reason("scan"), logging.INFO)
            return None
        stamp, angle_min, angle_max = full_scan.stamp, full_scan.angle_min, full_scan.angle_max
        range_min, range_max = full_scan.range_min, full_scan.range_max
        if np.size(full_scan.ranges) == 0:
            self.warn("scan-empty", "scan with no ranges ignored")
            return None
        if not all(math.isfinite(v) for v in (stamp, angle_min, angle_max)):
            self.warn("scan-angles", f"scan with non-finite stamp or angles ignored (t={stamp}, "
                      f"angle_min={angle_min}, angle_max={angle_max})")
            return None
        last_odom = self._last_odom_stamp
        if last_odom is not None and stamp < last_odom - self.params.odom_max_gap:
            self.warn("scan-stale", f"scan stamped {last_odom - stamp:.2f} s before the latest odometry ignored "
                      "(a clock jump or a stale message; odometry going back too resets the reference)")
            return None
        if not (math.isfinite(range_min) and math.isfinite(range_max) and 0 <= range_min < range_max):
            self.warn("scan-limits", f"scan range limits [{range_min}, {range_max}] are unusable: "
                      f"using [0, {self.filter.sensor_model.max_range:.2f}] m")
            range_min, range_max = 0.0, self.filter.sensor_model.max_range
        with self._lock:
            self._apply_motion(np.zeros(3))
            moved = (self._since_update[0] >= self.params.update_min_distance
                     or self._since_update[1] >= self.params.update_min_angle)
            if not (moved or self._force_update):
                return None
            scan = downsample_scan(full_scan, self.params.num_beams_per_particle, range_min, range_max)
            if not np.isfinite(scan.ranges).any():
                self.warn("scan-invalid", "scan with no valid range (all NaN, inf or out of limits) ignored")
                return None
            result = self.filter.sensor_update(scan.ranges, scan.angles)
            if not result.ok:
                self._impossible_scans += 1
                if self._impossible_scans >= self.params.max_impossible_scans:
                    self.log.warning(f"{self._impossible_scans} scans in a row gave every particle likelihood 0 "
                                     "(all off the map or in walls): re-spreading particles over the free space")
                    self._impossible_scans = 0
                    self.recoveries += 1
                    self._initialize_global_locked(stamp)
                else:
                    self.warn("scan-degenerate", "every particle has likelihood 0 for this scan: weights kept")
                return None
            self._impossible_scans = 0
            self._force_update = False
            self._since_update[:] = 0.0
            est: Estimate = self.filter.estimate()
            est = self._check_health(est, scan, range_min, range_max, stamp)
            self._estimate = PoseEstimate(stamp, est.pose, est.covariance)
            return self._estimate
