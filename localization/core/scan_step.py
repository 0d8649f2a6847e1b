"""The scan step: bring the particles to a scan's time and, when the update policy says so, update them.

For a scan at time t_s (scan clock) with the particles at t_filter:

    motion     particles ← particles ⊕ (Δ piece + ε) for each constant-twist piece of (t_filter, t_s]
               (``MotionModel``; exactly back, without noise, when t_s < t_filter)
    policy     s, φ = path length and rotation since the last update (the odometry over (t_update, t_s]);
               ``UpdatePolicy.reason`` decides
    beams      ~num_beams_per_particle beams; no return (inf) = a max-range reading at the scan's range_max
    seed       a pending global spread is re-seeded from these beams (``GlobalSeeder``)
    deskew     beam b cast from the laser pose at its own time t_b = stamp + i_b · time_increment:
               δ_b = L⁻¹ ⊕ Δ_b ⊕ L, Δ_b the robot's arc under the odometry twist at t_s over t_b − t_s
    update     log w ← log w + log p(z | x) / squash; resample (``MonteCarloLocalizer``; the first update after
               an initial pose in tempered stages, ``initial_update_stages``); an update that
               jumps from the published pose to a place the scan fits no clearly better is undone (``recovery``)
    judge      converged / tracking / holding, and a challenger's search, update and switch
               (``RecoveryPolicy``); while holding, the scan updates only the challenger: the cloud
               moves on odometry

Every particle at likelihood 0 for ``max_impossible_scans`` scans in a row asks for a re-spread
(``StepOutcome.respread``): no pose of the cloud is possible at all.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from localization.core.filter.mcl import Estimate, MonteCarloLocalizer
from localization.core.geometry import compose, integrate_twists, inverse
from localization.core.global_seeder import GlobalSeeder
from localization.core.occupancy_map import OccupancyMap
from localization.core.policies import UpdatePolicy
from localization.core.recovery import RecoveryPolicy, is_jump
from localization.core.scan import Scan, ScanData, downsample_scan, first_beam_time, sweep_increment
from localization.core.timeline import OdometryTimeline, PoseEstimate


@dataclass(frozen=True)
class StepOutcome:
    estimate: Estimate | None = None  # after a sensor update (None: no update)
    respread: bool = False  # every particle impossible, scan after scan: spread the particles globally
    switched: Estimate | None = None  # a challenger won: the cloud moved there (its estimate)
    # with an estimate: the scan's beams the update used, their range limits (m) and deskew offsets
    beams: Scan | None = None
    range_limits: tuple[float, float] | None = None
    offsets: np.ndarray | None = None  # (B, 3); None: a rigid scan
    refused: bool = False  # the update jumped to a place the scan fits no clearly better: undone (moved on odometry)
    jumped: bool = False  # the update jumped to a place the scan fits clearly better: kept, to be published as a glide
    published: PoseEstimate | None = None  # the published pose carried to the scan's time, when the jump check read it


def usable_beams(scan: ScanData, num_beams: int, model_max_range: float, warn, angle_step: int = 0):
    """The downsampled beams of a scan (``num_beams`` evenly spread, or every ``angle_step``-th) and its
    range limits (None, and a warning, when no beam is valid); unusable limits fall back to [0, the
    sensor model's max range]."""
    rmin, rmax = scan.range_min, scan.range_max
    if not (math.isfinite(rmin) and math.isfinite(rmax) and 0 <= rmin < rmax):
        warn("scan-limits", f"scan range limits [{rmin}, {rmax}] are unusable: using [0, {model_max_range:.2f}] m")
        rmin, rmax = 0.0, model_max_range
    beams = downsample_scan(scan, num_beams, rmin, rmax, angle_step)
    if not np.isfinite(beams.ranges).any():
        warn("scan-invalid", "scan with no valid range (all NaN, inf or out of limits) ignored")
        return None
    return beams, rmin, rmax


def deskew_offsets(scan: ScanData, t_s: float, idx, twist, laser_offset, stamp: str = "first_beam",
                   stamp_offset: float = 0.0):
    """Per-beam laser motion δ_b = L⁻¹ ⊕ Δ_b ⊕ L (B, 3) from t_s to each used beam's own time
    t_b = t_0 + i_b · time_increment (t_0 the first beam's time under the scan_stamp convention), Δ_b
    the robot's arc under ``twist`` (the odometry's at t_s), L the laser pose; None without sweep timing."""
    sweep = sweep_increment(scan)
    if not sweep > 0:
        return None
    t0 = first_beam_time(scan, stamp, stamp_offset)
    robot = integrate_twists(twist[0], twist[1], twist[2], t0 + np.asarray(idx) * sweep - t_s)
    laser = np.asarray(laser_offset, dtype=float)
    return compose(inverse(laser), compose(robot, laser))


class ScanStep:
    def __init__(self, pf: MonteCarloLocalizer, timeline: OdometryTimeline, policy: UpdatePolicy,
                 seeder: GlobalSeeder, recovery: RecoveryPolicy, params, warn):
        self.pf, self.timeline, self.policy, self.seeder, self.recovery = pf, timeline, policy, seeder, recovery
        self.params, self.warn = params, warn
        self.t_filter: float | None = None  # s, scan clock: the time the particles describe
        self.t_update: float | None = None  # s, scan clock: the last sensor update
        self.impossible = 0  # scans in a row that gave every particle likelihood 0
        self.refused_jumps = 0  # updates undone: they jumped to a place the scan fits no clearly better
        self.temper_next = False  # the next sensor update is tempered (the first after an initial pose)

    def restart(self, t: float | None) -> None:
        """The particles were (re-)initialised at time t."""
        self.t_filter = self.t_update = t
        self.impossible = 0

    def move_to(self, t: float) -> None:
        """Particles (and a challenger's) to time t through the odometry (noise per piece; exactly
        back if t is older). A t on another clock than the odometry's (a stamp jump) moves nothing:
        the motion across the jump is unknown."""
        t_from = self.timeline.usable(self.t_filter)
        if t_from is not None and not self.timeline.empty and self.timeline.usable(t) == t:
            clouds = [c for c in (self.pf, self.recovery.challenger) if c is not None]
            if t < t_from:
                for cloud in clouds:
                    cloud.shift(inverse(self.timeline.motion(t, t_from)))
            dts, twists, slips = self.timeline.slip_segments(t_from, t)
            for delta, (slip, slip_var) in zip(integrate_twists(twists[:, 0], twists[:, 1], twists[:, 2], dts),
                                               slips):
                for cloud in clouds:
                    cloud.motion_update(delta, slip, slip_var)
        self.t_filter = t

    def run(self, scan: ScanData, t_s: float, occupancy_map: OccupancyMap, global_mode: bool,
            check_jump: bool = False) -> StepOutcome:
        """``check_jump``: an update that jumps from the published pose (carried to t_s) is undone when the
        scan fits the new place no clearly better (``_refuse_jump``), else kept and reported (``jumped``)."""
        p, model, pf, recovery = self.params, self.pf.sensor_model, self.pf, self.recovery
        self.move_to(t_s)
        t_last = self.timeline.usable(self.t_update)
        distance, angle = self.timeline.travel(t_s if t_last is None else t_last, t_s)
        twist = self.timeline.twist_at(t_s)
        speed, yaw_rate = math.hypot(twist[0], twist[1]), twist[2]
        if self.policy.reason(distance, angle, speed, yaw_rate) is None:
            return StepOutcome()
        usable = usable_beams(scan, p.num_beams_per_particle, model.max_range, self.warn, p.angle_step)
        if usable is None:
            return StepOutcome()
        b, rmin, rmax = usable
        beams = (b.ranges, b.angles, rmin, rmax)
        self.seeder.seed(pf, occupancy_map, b.ranges, b.angles, rmax)
        offsets = deskew_offsets(scan, t_s, b.indices, twist, model.laser_offset, p.scan_stamp,
                                 p.scan_stamp_offset) if p.deskew and model.supports_deskew else None
        published = self.timeline.pose_at(t_s) if check_jump and not global_mode else None
        guard = published is not None and not recovery.holding
        before = pf.snapshot() if guard else None
        if not recovery.holding and not self._update(b.ranges, b.angles, offsets, rmax).ok:
            self.impossible += 1
            if self.impossible < p.max_impossible_scans:
                self.warn("scan-degenerate", "every particle has likelihood 0 for this scan: weights kept")
                return StepOutcome()
            self.warn("scan-impossible", f"{self.impossible} scans in a row gave every particle likelihood 0 (all "
                      "off the map or in walls): re-spreading particles over the free space")
            return StepOutcome(respread=True)
        self.impossible, self.t_update = 0, t_s
        self.policy.updated(speed, yaw_rate)
        est = pf.estimate()  # (holding: the cloud moved on odometry only)
        jumped = guard and is_jump(published, est.pose, p.recovery_jump_glide)
        refused = jumped and self._refuse_jump(published, est.pose, beams, before)
        if refused:
            est = pf.estimate()
        verdict = recovery.judge(est.pose, est.covariance, beams, global_mode)
        if verdict.converged:
            self.seeder.converged(pf, est.pose)
        if verdict.message:
            self.warn("recovery-lost" if verdict.lost else "recovery-back", verdict.message)
        return StepOutcome(estimate=est, switched=self._challenge(occupancy_map, b, beams, offsets, t_s,
                                                                  verdict.agreement, distance),
                           beams=b, range_limits=(rmin, rmax), offsets=offsets, refused=refused,
                           jumped=jumped and not refused, published=published)

    def _update(self, ranges, angles, offsets, range_max):
        """The cloud's sensor update: tempered when ``temper_next`` (then cleared once it succeeded)."""
        if not self.temper_next:
            return self.pf.sensor_update(ranges, angles, offsets, range_max=range_max)
        result = self.pf.tempered_update(ranges, angles, offsets, range_max, self.params.initial_update_stages)
        self.temper_next = self.temper_next and not result.ok
        return result

    def _refuse_jump(self, published, pose, beams, before) -> bool:
        """Undo an update that jumped (``recovery.is_jump``) from the published pose to a place the scan
        fits no clearly better: the scan–map agreement at ``pose`` below the published pose's plus
        ``recovery_margin``. True: undone."""
        moved, kept = self.recovery.score(pose, beams), self.recovery.score(published.pose, beams)
        if not moved < kept + self.params.recovery_margin:
            return False
        self.pf.restore(before)
        self.refused_jumps += 1
        self.warn("jump-refused", f"a sensor update moved the estimate {math.dist(pose[:2], published.pose[:2]):.2f} m "
                  f"to a place the scan fits no clearly better (agreement {moved:.2f}, {kept:.2f} at the published "
                  "pose): update undone, the pose moves on odometry")
        return True

    def _challenge(self, occupancy_map: OccupancyMap, b, beams, offsets, t_s: float, main_agreement: float,
                   distance: float):
        """While holding: search for, update and judge a challenger; its estimate when it wins."""
        recovery = self.recovery
        if recovery.search_due(t_s):
            recovery.start(self.seeder.challenger(self.pf, occupancy_map, b.ranges, b.angles, beams[3]), t_s)
            return None  # its first update is the next scan's
        if recovery.challenger is None:
            return None
        recovery.challenger.sensor_update(b.ranges, b.angles, offsets, range_max=beams[3])
        verdict = recovery.challenge(main_agreement, beams, t_s, distance)
        if verdict != "switch":
            return None
        won, est = recovery.challenger, recovery.challenger.estimate()
        self.pf.set_particles(won.particles)
        recovery.restart()
        self.warn("recovery-switch", f"recovery: the scans fit ({est.pose[0]:.2f}, {est.pose[1]:.2f}) clearly better "
                  f"for {self.params.recovery_confirm_updates}+ updates over {self.params.recovery_confirm_distance} "
                  "m: the cloud moves there")
        return est
