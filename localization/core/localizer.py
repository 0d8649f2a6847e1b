"""The localizer: what to do with each incoming message, shared by the node and the replay tool.

It owns the map, the models and the particle filter, and turns a stream of
(odometry twist, stamp) and (scan, stamp) into pose estimates:

- odometry: kept in a short history on the scan's clock (``core.odometry.OdometryBuffer``: stamps
  shifted by ``odom_time_offset``, twist corrected by the speed / yaw-rate scales and bias); the
  twist of message k holds from the previous *message stamp* to its own (never the wall clock,
  so bags replay right at any rate) and the particles are moved through it, one constant-twist
  arc per odometry period (motion noise per period). A stamp going backwards or a gap longer
  than ``odom_max_gap`` resets the reference instead of moving particles;
- scan (``align_odometry``): the particles are moved to the scan's own time t_s (its stamp, or
  the middle of its sweep when ``time_increment`` > 0) through the odometry history, the last
  twist extrapolated when the scan is newer than the newest odometry, or moved back (exactly,
  no noise) when odometry newer than the scan has been applied already. Then, once the car has
  moved ``update_min_distance`` / ``update_min_angle`` since the last update (always right after
  an initialisation, and once where the car comes to a stop: below ``STANDING_SPEED`` and
  ``STANDING_YAW_RATE``), the downsampled scan updates the filter (+ resampling) there — each beam
  cast from the laser pose at its own time with ``deskew`` — the estimate is stamped t_s, and the
  odometry newer than t_s is applied again after the update;
- what the node publishes on each odometry message (``on_odometry``, ``estimate``): the latest
  sensor-corrected estimate carried forward with the odometry received since, to the odometry
  message's stamp (a controller always gets a current pose);
- nothing happens before a map and an initial pose (or a global initialisation) have arrived;
- health and recovery (``localization.health``): after each sensor update of a converged cloud the
  estimate is scored against the scan (``health``); a lost filter is re-spread over the free space
  with ``global_num_particles``, which shrink back to ``num_particles`` once the cloud converges.

Thread safety: the node may call ``on_odometry`` while ``on_scan`` runs. Odometry that arrives
during a sensor update only goes into the history (its own small lock) and is applied to the
particles by the next call that holds the filter lock; the returned estimate is the last one
carried forward through the history, so odometry never waits for a slow scan.
"""
from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass

import numpy as np

from localization.core.compile_cache import ensure_compiled
from localization.core.filter.global_init import ScanSeedParams, seed_from_scan
from localization.core.filter.kld import KLDSampler
from localization.core.filter.mcl import Estimate, MonteCarloLocalizer
from localization.core.geometry import compose, integrate_twist, integrate_twists, inverse
from localization.core.health import AgreementScorer, HealthMonitor, cloud_spread
from localization.core.motion import MotionModel, MotionNoiseParams
from localization.core.occupancy_map import MapError, OccupancyMap
from localization.core.odometry import OdometryBuffer, TwistData
from localization.core.parameters import Parameters
from localization.core.scan import ScanData, downsample_indices, downsample_scan, scan_time, sweep_increment
from localization.core.sensors.beam import BeamModel, BeamModelParams
from localization.core.sensors.likelihood_field import LikelihoodFieldModel, LikelihoodFieldParams

MAX_INITIAL_VARIANCE = 1.0e4  # m², rad²: an initial-pose covariance entry beyond this is not a pose estimate
STANDING_SPEED, STANDING_YAW_RATE = 0.05, 0.05  # m/s, rad/s: below both the car has stopped (one more update)


@dataclass
class PoseEstimate:
    stamp: float  # seconds: the time of the data the estimate reflects
    pose: np.ndarray  # (3,)
    covariance: np.ndarray  # (3, 3)


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
        p = self.params
        self._odom = OdometryBuffer(p.odom_time_offset, p.odom_speed_scale, p.odom_yaw_rate_scale,
                                    p.odom_yaw_rate_bias)
        self._odom_lock = threading.Lock()  # guards _odom and _odom_now (on_odometry runs during on_scan)
        self._odom_now: float | None = None  # stamp of the newest odometry message in the history
        self._t_filter: float | None = None  # the time (scan clock) the particles describe
        self._estimate_t: float | None = None  # the time _estimate's pose describes
        self._inits = 0  # (re-)initialisations of the cloud
        self._last_odom_stamp: float | None = None
        self._odom_before_jump: float | None = None  # the reference before a stamp jump (one bad stamp?)
        self._since_update = np.zeros(2)  # distance, angle travelled since the last sensor update
        self._force_update = False
        self._stop_updated = False  # a sensor update happened since the car stopped
        self._estimate: PoseEstimate | None = None
        self._impossible_scans = 0
        self.health_monitor = HealthMonitor.from_params(self.params)
        self._scorer: AgreementScorer | None = None
        self._seed_pending = False  # global_init scan: the next scan seeds the global spread
        self.recoveries = 0  # re-spreads after the filter was judged lost (or every particle impossible)
        self.map_pending = False  # a map arrived and its ray caster is being prepared (prepare_ray_caster)
        self._corrections: list[PoseEstimate] = []  # sensor-corrected estimates not yet taken

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
        """The latest sensor-corrected estimate carried forward with the odometry received since,
        to the newest odometry message's stamp (what the node publishes on each odometry message)."""
        with self._odom_lock:  # one consistent snapshot (on_scan may be replacing the estimate)
            est, est_t, now = self._estimate, self._estimate_t, self._odom_now
        if est is None or est_t is None or now is None:
            return est
        return self._carried(est, est_t, now)

    def estimate_at(self, t: float) -> PoseEstimate | None:
        """The latest sensor-corrected estimate moved through the odometry history to time t,
        backwards too (e.g. the pose when a scan was taken, ``scan_time``: what to score it with)."""
        with self._odom_lock:
            est, est_t = self._estimate, self._estimate_t
        if est is None or est_t is None or not math.isfinite(t):
            return est
        with self._odom_lock:
            t_from = self._history_time(est_t)
            if t_from is None:
                return est
            delta = self._odom.motion(t_from, t)
        return PoseEstimate(t, compose(est.pose, delta), est.covariance)

    def _carried(self, est: PoseEstimate, est_t: float, t: float) -> PoseEstimate:
        """``est`` (describing time est_t) moved forward to time t through the odometry history."""
        with self._odom_lock:
            t_from = self._history_time(est_t)
            if t_from is None or not t > t_from:
                return est
            delta = self._odom.motion(t_from, t)
        return PoseEstimate(t, compose(est.pose, delta), est.covariance)

    def _history_time(self, t: float | None) -> float | None:
        """t if the odometry history can move the particles from it; after a clock jump (t far
        outside the history) the history's start: the motion across the jump is lost (odom lock held)."""
        oldest, latest, gap = self._odom.oldest, self._odom.latest, self.params.odom_max_gap
        if oldest is None:
            return t
        if t is None or t < oldest - gap or t > latest + gap:
            return oldest
        return t

    @property
    def num_particles(self) -> int:
        return self.filter.num_particles

    def particles(self) -> np.ndarray:
        """A copy of the particles (N, 3) as they are now (read under the filter lock)."""
        with self._lock:
            return np.array(self.filter.particles, dtype=float, copy=True)

    @property
    def laser_offset(self) -> np.ndarray:
        """The laser pose (x, y, yaw) in the robot frame the sensor model uses."""
        return np.array(self.filter.sensor_model.laser_offset, dtype=float, copy=True)

    def take_corrections(self) -> list[PoseEstimate]:
        """The sensor-corrected estimates made since the last call, oldest first, each stamped with
        the time it describes (a scan's time on the scan clock). The node publishes them on /pf/pose."""
        with self._odom_lock:
            out, self._corrections = self._corrections, []
        return out

    def begin_map_preparation(self) -> None:
        """A map is being prepared elsewhere (off-thread): inputs are reported as waiting for it."""
        self.map_pending = True

    def cancel_map_preparation(self) -> None:
        """Preparing the pending map failed: inputs are no longer reported as waiting for it."""
        self.map_pending = False

    # ------------------------------------------------------------------ inputs
    def set_map(self, occupancy_map: OccupancyMap, ray_caster=None) -> None:
        """Use a (new) map. Particles are kept if they stay valid, else re-initialised.
        A map without free space raises MapError and the previous map stays in use.
        ``ray_caster``: one made beforehand by ``prepare_ray_caster`` (e.g. off the callback thread)."""
        if len(occupancy_map.free_cells) == 0:
            raise MapError("map has no free cell (all unknown or occupied): ignored")
        if ray_caster is None:
            ensure_compiled(self.params, self.log)
        with self._lock:
            self.filter.sensor_model.set_map(occupancy_map, ray_caster)
            self.map_pending = False
            self.map = occupancy_map
            self._scorer = AgreementScorer(occupancy_map, self.filter.sensor_model.laser_offset,
                                           range_scale=self.params.lidar_scale_to_map_scale)
            self.health_monitor.reset()
            if self.filter.initialized:
                inside = ~occupancy_map.is_occupied_or_outside(self.filter.particles[:, :2])
                if not inside.any():
                    self.log.warning("new map: no particle lies in free space any more; waiting for a new initial pose")
                    self.filter.initialized = False
                    self._estimate = None
            elif self.params.global_localization:
                self._initialize_global_locked()

    # ------------------------------------------------------------------ node services (issue 11)
    def prepare_ray_caster(self, occupancy_map: OccupancyMap):
        """The sensor model's ``prepare``d map (a ray caster with its range table built or loaded, or
        the likelihood field's distance field): the slow part of ``set_map``, made without touching
        the filter, so a caller can run it on another thread and then call ``set_map(occupancy_map,
        prepared)``; ``map_pending`` is True meanwhile (inputs are reported as waiting for the table)."""
        self.map_pending = True
        ensure_compiled(self.params, self.log)
        return self.filter.sensor_model.prepare(occupancy_map)

    def set_laser_offset(self, offset) -> None:
        """The laser pose (x, y, yaw) in the robot frame, e.g. read from TF."""
        offset = np.asarray(offset, dtype=float).reshape(3)
        with self._lock:
            sensor = self.filter.sensor_model
            sensor.laser_offset = offset.copy()
            sensor.laser_offset_x, sensor.laser_offset_y, sensor.laser_offset_yaw = (float(v) for v in offset)
            if self._scorer is not None:
                self._scorer.laser_offset = offset.copy()

    def request_update(self) -> None:
        """The next scan updates the filter even without motion (nav2's request_nomotion_update)."""
        with self._lock:
            self._force_update = True

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
            if not (np.all(np.isfinite(cov)) and np.trace(cov) > 0 and np.abs(cov).max() <= MAX_INITIAL_VARIANCE):
                self.log.warning(f"initial pose covariance {np.diag(cov).tolist()} (diagonal) is not a usable spread "
                                 "(non-finite, zero, or beyond 1e4): using initial_std_xy / initial_std_theta")
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

    @property
    def global_particle_count(self) -> int:
        """Particles of a global spread (start, service, recovery): max_particles with
        adaptive_particles (KLD then shrinks the cloud as it converges), else global_num_particles."""
        return self.params.max_particles if self.params.adaptive_particles else self.params.global_num_particles

    def _initialize_global_locked(self, stamp: float = 0.0) -> bool:
        if self.map is None:
            self.log.warning("global localization requested before a map arrived: will spread once it does")
            return False
        self.filter.resize(self.global_particle_count)
        self.filter.initialize_uniform(self.map)
        self.global_mode = True
        self._after_init(stamp)
        self._seed_pending = self.params.global_init == "scan"  # the next scan proposes the poses
        return True

    def _seed_from_scan(self, scan) -> None:
        """global_init scan (lock held): replace the uniform spread by particles drawn from the
        poses the scan fits (``filter.global_init``), before the scan's own sensor update."""
        self._seed_pending = False
        t0 = time.perf_counter()
        seeds = seed_from_scan(self.map, self.filter.sensor_model, scan.ranges, scan.angles,
                               self.filter.num_particles, self.filter.rng, ScanSeedParams.from_parameters(self.params))
        self.filter.set_particles(seeds.poses)
        self.log.info(f"global localization: {seeds.lattice_poses} lattice poses scored against the scan in "
                      f"{time.perf_counter() - t0:.2f} s; {len(seeds.poses)} particles drawn around the best "
                      f"{len(seeds.candidates)}")

    def _after_init(self, stamp: float) -> None:
        self._inits += 1
        self.health_monitor.reset(keep_slow=True)
        self._force_update = True
        self._since_update[:] = 0.0
        with self._odom_lock:  # the particles describe the pose's stamp (the newest odometry's time if unusable)
            self._t_filter = self._history_time(stamp) if len(self._odom) else None
        est = self.filter.estimate()
        with self._odom_lock:
            self._estimate = PoseEstimate(stamp, est.pose, est.covariance)
            self._estimate_t = stamp if self._t_filter is None else self._t_filter

    def on_odometry(self, twist: TwistData) -> PoseEstimate | None:
        """Add an odometry message to the history and move the particles through it; returns the
        latest sensor-corrected estimate carried forward to the message's stamp."""
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
        before_jump, self._odom_before_jump = self._odom_before_jump, None
        max_gap = self.params.odom_max_gap
        if last is not None:
            dt = stamp - last
            if not 0.0 < dt <= max_gap and before_jump is not None and 0.0 < stamp - before_jump <= max_gap:
                dt, before_jump = stamp - before_jump, None  # one message with a bad stamp: continue from before it
            if dt <= 0.0 or dt > max_gap:
                self._odom_before_jump = last
                self.warn("odom-jump", f"odometry stamp jumped by {dt:+.3f} s (bag loop or sensor restart): "
                          "motion reference reset, particles not moved")
                return None
        with self._odom_lock:
            if last is None or before_jump is not None:  # the first message, or the clock jumped at `last`:
                self._odom.reset()  # a new history from there (the motion across the jump is lost)
                if last is not None:
                    self._odom.add(TwistData(last, 0.0, 0.0, 0.0))
            self._odom.add(twist)
            self._odom_now = stamp
            keep = [t for t in (self._t_filter, self._estimate_t, self._odom.latest) if t is not None]
            self._odom.trim(min(keep) - max_gap)
        if last is None or not self.ready:
            if not self.ready:
                self.warn("odom-not-ready", self._not_ready_reason("odometry"), logging.INFO)
            return None
        if self._lock.acquire(blocking=False):  # else a sensor update is running: it applies the odometry later
            try:
                self._advance_locked(self._odom.latest)
            finally:
                self._lock.release()
        return self.estimate

    def _advance_locked(self, t: float | None) -> None:
        """Move the particles forward to time t through the odometry history, one constant-twist
        arc (with motion noise) per odometry period (lock held; never backwards)."""
        with self._odom_lock:
            t_from = self._history_time(self._t_filter)
            if t is None or t_from is None or not t > t_from:
                self._t_filter = t_from if t_from is not None else t
                return
            dts, twists = self._odom.segments(t_from, t)
        for dt, (vx, vy, wz) in zip(dts, twists):
            delta = integrate_twist(vx, vy, wz, dt)
            self.filter.motion_update(delta)
            self._since_update += (math.hypot(delta[0], delta[1]), abs(delta[2]))
        self._t_filter = t
        with self._odom_lock:
            est, est_t = self._estimate, self._estimate_t
        if est is not None and est_t is not None and est_t < t - 0.5 * self.params.odom_max_gap:
            carried = self._carried(est, est_t, t)  # keep the history short
            with self._odom_lock:
                self._estimate, self._estimate_t = carried, t

    def scan_time(self, scan: ScanData) -> float:
        """``core.scan.scan_time``: the stamp, or the middle of the sweep when it is timed."""
        return scan_time(scan)

    def _move_to_scan_locked(self, t_s: float | None):
        """Bring the particles to the scan's time t_s (lock held): forward through the odometry
        (the last twist extrapolated past the newest message), or exactly back when odometry newer
        than the scan was applied already — that motion is returned, to apply again after the
        update. Without alignment (t_s None) they go to the newest odometry (as before issue 10)."""
        if t_s is None:
            with self._odom_lock:
                latest = self._odom.latest
            self._advance_locked(latest)
            return None
        self._advance_locked(t_s)
        if self._t_filter is None or not t_s < self._t_filter:
            return None
        with self._odom_lock:
            later = self._odom.motion(t_s, self._t_filter)
        self.filter.particles = compose(self.filter.particles, inverse(later))
        return later

    def _deskew_offsets(self, full_scan: ScanData, t_s: float, idx=None):
        """Per-beam laser motion δ_b (B, 3) in the laser frame from t_s to each used beam's own
        time t_b = stamp + i_b · time_increment (i_b: ``idx``, the downsampled beams' indices):
        δ_b = L⁻¹ ⊕ Δ_b ⊕ L, Δ_b the robot's constant-twist arc (the odometry twist at t_s) over
        t_b − t_s, L the laser offset. None without sweep timing."""
        sweep = sweep_increment(full_scan)
        if not (sweep > 0 and self.params.deskew and getattr(self.filter.sensor_model, "supports_deskew", False)):
            return None
        if idx is None:
            idx = downsample_indices(np.size(full_scan.ranges), self.params.num_beams_per_particle)
        with self._odom_lock:
            vx, vy, wz = self._odom.twist_at(t_s)
        robot = integrate_twists(vx, vy, wz, full_scan.stamp + idx * sweep - t_s)
        laser = np.asarray(self.filter.sensor_model.laser_offset, dtype=float)
        return compose(inverse(laser), compose(robot, laser))

    @property
    def global_mode(self) -> bool:
        """Particles spread globally (start, service or recovery), not yet converged. The filter's
        ``kld_hold`` is the same flag: with adaptive_particles a global spread keeps max_particles
        until it converges."""
        return self.filter.kld_hold

    @global_mode.setter
    def global_mode(self, value: bool) -> None:
        self.filter.kld_hold = bool(value)

    def _check_health(self, est, scan, range_min: float, range_max: float, stamp: float):
        """After a sensor update (lock held): shrink a converged global cloud back to num_particles;
        score a converged estimate against the scan and re-spread globally when the filter is lost."""
        if self.global_mode:
            if cloud_spread(est.covariance) >= self.params.global_converged_std:
                return est  # still spread: the mean pose of many hypotheses says nothing yet
            self.global_mode = False
            if self.filter.kld is None:  # adaptive_particles: the KLD sampler shrinks the cloud itself
                self.filter.resize(self.params.num_particles)
            self.health_monitor.reset(keep_slow=True)
            self.log.info(f"global localization converged at ({est.pose[0]:.2f}, {est.pose[1]:.2f}, "
                          f"{est.pose[2]:.2f}): {self.filter.num_particles} particles")
        agreement = self._scorer.score(est.pose, scan.ranges, scan.angles, range_min, range_max)
        if self.health_monitor.update(agreement) and self.params.recovery:
            m = self.health_monitor
            self.log.warning(f"localization lost: scan-map agreement {m.fast:.2f} (long-term {m.slow:.2f}) for "
                             f"{m.low_count} updates; re-spreading {self.global_particle_count} particles "
                             "over the free space (recovery)")
            self.recoveries += 1
            self._initialize_global_locked(stamp)
            est = self.filter.estimate()
        return est

    def _not_ready_reason(self, what: str) -> str:
        if self.map_pending:
            return f"{what} ignored: waiting for the range table of the map (being built or loaded)"
        if self.map is None:
            return f"{what} ignored: no map received yet"
        return f"{what} ignored: waiting for an initial pose (/initialpose) or global localization"

    def on_scan(self, full_scan: ScanData) -> PoseEstimate | None:
        """Sensor update (+ resampling) from a full scan at the scan's own time; returns the new
        estimate (stamped with that time), or None when the filter is not ready or the car has not
        moved enough since the last update."""
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
        t_s = self.scan_time(full_scan) if self.params.align_odometry else None
        with self._lock:
            later = self._move_to_scan_locked(t_s)  # odometry newer than the scan, taken back until the update
            inits = self._inits
            try:
                return self._update_locked(full_scan, t_s, range_min, range_max)
            finally:
                if later is not None and self._inits == inits:  # apply the later odometry again
                    self.filter.particles = compose(self.filter.particles, later)

    def _update_locked(self, full_scan: ScanData, t_s: float | None, range_min: float,
                       range_max: float) -> PoseEstimate | None:
        """on_scan's sensor update, the particles at the scan's time t_s (lock held; t_s None:
        without alignment, at the newest odometry, the estimate stamped with the scan's stamp)."""
        stamp = full_scan.stamp if t_s is None else t_s
        moved = (self._since_update[0] >= self.params.update_min_distance
                 or self._since_update[1] >= self.params.update_min_angle)
        with self._odom_lock:
            vx, vy, wz = self._odom.twist_at(stamp if self._t_filter is None else self._t_filter)
        standing = math.hypot(vx, vy) < STANDING_SPEED and abs(wz) < STANDING_YAW_RATE
        self._stop_updated = self._stop_updated and standing
        stopped_here = standing and not self._stop_updated and self._since_update.any()  # once where it stopped
        if not (moved or self._force_update or stopped_here):
            return None
        scan = downsample_scan(full_scan, self.params.num_beams_per_particle, range_min, range_max)
        if not np.isfinite(scan.ranges).any():
            self.warn("scan-invalid", "scan with no valid range (all NaN, inf or out of limits) ignored")
            return None
        if self._seed_pending and self.global_mode:
            self._seed_from_scan(scan)
        offsets = None if t_s is None else self._deskew_offsets(full_scan, t_s, scan.indices)
        result = self.filter.sensor_update(scan.ranges, scan.angles, offsets)
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
        self._stop_updated = standing
        self._since_update[:] = 0.0
        est: Estimate = self.filter.estimate()
        est = self._check_health(est, scan, range_min, range_max, stamp)
        with self._odom_lock:
            self._estimate = PoseEstimate(stamp, est.pose, est.covariance)
            self._estimate_t = self._t_filter if t_s is None else t_s
            self._corrections.append(self._estimate)
        return self._estimate
