"""The scan pipeline: one scan at its time t_s (scan clock), top to bottom, each stage once.

    move      particles ← particles ⊕ (Δ piece + ε) for each constant-twist piece of (t_filter, t_s]
              (``MotionModel``; exactly back, without noise, when t_s < t_filter); a challenger moves too
    gate      s, φ = path length and rotation since the last update; ``UpdatePolicy.reason`` decides
    beams     ~num_beams_per_particle beams; no return (inf) = a max-range reading at the scan's range_max;
              a pending global spread is seeded from them (``GlobalSeeder``)
    deskew    beam b cast from the laser pose at its own time t_b = t_0 + i_b · time_increment:
              δ_b = L⁻¹ ⊕ Δ_b ⊕ L, Δ_b the robot's arc under the odometry twist at t_s over t_b − t_s
    weigh     log w ← log w + log p(z | x) / squash, normalised (the first update after an initial pose in
              tempered stages, ``initial_update_stages``); not while holding
    resample  when the effective sample size is low (``MonteCarloLocalizer``)
    estimate  the weighted mean and covariance
    decide    ``Recovery.decide``: one ``Decision`` (track, undo, hold, switch, re-spread, spread, converge)
    apply     the decision, in one place (``_apply``): the cloud restored, replaced or re-spread, the range
              scale learnt while tracking, the published estimate (gliding after a switch or a kept jump)
              becomes the timeline's anchor

A scan that is not due, or has no valid beam, skips to ``apply`` with ``Action.SKIP`` (a glide goes on).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import partial
from typing import NamedTuple

import numpy as np

from localization.core.cost import NO_COST, UpdateCost
from localization.core.filter.mcl import MonteCarloLocalizer
from localization.core.geometry import compose, integrate_twists, inverse
from localization.core.localizer.initial_pose import InitialPose
from localization.core.localizer.policies import UpdatePolicy, UpdatePolicyParams
from localization.core.localizer.range_scale import RangeScaleEstimator
from localization.core.localizer.recovery import Action, Beams, Decision, Recovery, SwitchGlide, Update
from localization.core.localizer.seeder import GlobalSeeder
from localization.core.localizer.timeline import OdometryTimeline, PoseEstimate
from localization.core.models.sensor import SensorModel
from localization.core.occupancy_map import OccupancyMap
from localization.core.scan import ScanData, beam_times, downsample_scan

SKIPPED = Decision(Action.SKIP)
LEARNS = (Action.TRACK, Action.CONVERGE)  # the range scale is learnt from these updates (tracking)


class Gate(NamedTuple):
    """A scan the update policy lets through: the motion since the last sensor update, the twist at its time."""

    travelled: float  # m
    twist: np.ndarray  # (vx, vy, ω) of the odometry at the scan's time
    speed: float  # m/s
    yaw_rate: float  # rad/s


@dataclass(frozen=True)
class Used:
    """A scan the pipeline used: what was decided, the corrected estimate it published (None: none) and what
    it cost (``core.cost``: beams cast, passes over the cloud)."""

    action: Action
    estimate: PoseEstimate | None = None
    cost: UpdateCost = NO_COST


def usable_beams(scan: ScanData, num_beams: int, model_max_range: float, warn, angle_step: int = 0,
                 stamp: str = "first_beam", stamp_offset: float = 0.0) -> Beams | None:
    """The downsampled beams of a scan (``num_beams`` evenly spread, or every ``angle_step``-th): their
    ranges, angles, own times (``core.scan.beam_times``, under the scan_stamp convention) and the scan's
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
    times = beam_times(scan, beams.indices, stamp, stamp_offset)
    return Beams(beams.ranges, beams.angles, beams.indices, rmin, rmax, times)


def deskew_offsets(times, t_s: float, twist, laser_offset):
    """Per-beam laser motion δ_b = L⁻¹ ⊕ Δ_b ⊕ L (B, 3) from t_s to each used beam's own time t_b
    (``times``, scan clock), Δ_b the robot's arc under ``twist`` (the odometry's at t_s), L the laser
    pose; None without sweep timing (``times`` None)."""
    if times is None:
        return None
    robot = integrate_twists(twist[0], twist[1], twist[2], times - t_s)
    laser = np.asarray(laser_offset, dtype=float)
    return compose(inverse(laser), compose(robot, laser))


class ScanPipeline:
    """The scan's way through the filter (module docstring) and the cloud's (re)initialisation."""

    def __init__(self, params, pf: MonteCarloLocalizer, model: SensorModel, timeline: OdometryTimeline, warn, log):
        self.params, self.pf, self.model, self.timeline, self.warn = params, pf, model, timeline, warn
        self.policy = UpdatePolicy(UpdatePolicyParams.from_parameters(params))
        self.seeder = GlobalSeeder(params, log)
        self.recovery = Recovery(params, partial(self.seeder.challenger, pf), warn)
        self.cost = model.cost = self.recovery.cost = pf.cost  # one meter: beams cast, passes (``core.cost``)
        self._weighed = (0, 0)  # (particles, beams) of this scan's sensor update (0, 0: none)
        self.glide = SwitchGlide(params.recovery_switch_step, params.recovery_switch_turn,
                                 params.recovery_switch_glide_max)
        self.range_scale = None  # RangeScaleEstimator (range_scale_estimation, a model that supports it)
        if params.range_scale_estimation:
            if model.supports_range_scale:
                self.range_scale = RangeScaleEstimator.from_parameters(params)
            else:
                log.info("range_scale_estimation: the likelihood field does not learn the range scale "
                         "(lidar_scale_to_map_scale as configured)")
        self.map: OccupancyMap | None = None
        self.t_filter: float | None = None  # s, scan clock: the time the particles describe
        self.t_update: float | None = None  # s, scan clock: the last sensor update
        self.impossible = 0  # scans in a row that gave every particle likelihood 0
        self.temper_next = False  # the next sensor update is tempered (the first after an initial pose)
        self.recoveries = 0  # switches and re-spreads
        self.refused_jumps = 0  # updates undone: they jumped to a place the scan fits no clearly better

    # ------------------------------------------------------------------ one scan
    def run(self, scan: ScanData, t_s: float) -> Used:
        """One scan at its time t_s, once the odometry reaches it (module docstring), with what it cost."""
        self.cost.take()  # counts from outside a scan (a map's warm-up, an initialisation) are not this scan's
        self._weighed = (0, 0)
        used = self._run(scan, t_s)
        return replace(used, cost=self.cost.take(*self._weighed))

    def _run(self, scan: ScanData, t_s: float) -> Used:
        global_mode = self.pf.kld_hold  # a global spread, not yet converged
        judged = not global_mode and self.params.recovery_jump_glide > 0.0 and not self.glide.active
        self.move_to(t_s)  # move
        gate = self._gate(t_s)  # gate
        if gate is None:
            return self._apply(SKIPPED, t_s)
        beams = self._beams(scan)  # beams
        if beams is None:
            return self._apply(SKIPPED, t_s)
        offsets = self._deskew(t_s, beams, gate.twist)  # deskew
        published = self.timeline.pose_at(t_s) if judged else None  # a jump is judged from the published pose
        before = self.pf.snapshot() if published is not None and not self.recovery.holding else None
        estimate = self._weigh(beams, offsets, t_s, gate)  # weigh, resample, estimate (None: impossible)
        update = Update(t_s, beams, offsets, gate.travelled, global_mode, estimate, self.impossible, before, published)
        return self._apply(self.recovery.decide(update), t_s, update)  # decide, apply

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
            pieces = integrate_twists(*np.ascontiguousarray(twists.T), dts)  # the columns in one copy
            if len(clouds) == 1:  # every piece in one pass over the cloud
                self.pf.motion_updates(pieces, slips)
            else:  # piece by piece, each cloud in turn: the draws in the order they always came
                for delta, (slip, slip_var) in zip(pieces, slips):
                    for cloud in clouds:
                        cloud.motion_update(delta, slip, slip_var)
        self.t_filter = t

    def _gate(self, t_s: float) -> Gate | None:
        """The motion since the last sensor update and the twist at t_s, when the update policy lets this
        scan update the filter (None: it does not)."""
        t_last = self.timeline.usable(self.t_update)
        distance, angle = self.timeline.travel(t_s if t_last is None else t_last, t_s)
        twist = self.timeline.twist_at(t_s)
        gate = Gate(distance, twist, math.hypot(twist[0], twist[1]), twist[2])
        return None if self.policy.reason(distance, angle, gate.speed, gate.yaw_rate) is None else gate

    def _beams(self, scan: ScanData) -> Beams | None:
        """The beams the update uses (None: no valid one); a pending global spread is seeded from them."""
        p = self.params
        beams = usable_beams(scan, p.num_beams_per_particle, self.model.max_range, self.warn, p.angle_step,
                             p.scan_stamp, p.scan_stamp_offset)
        if beams is not None:
            self.seeder.seed(self.pf, self.map, beams.ranges, beams.angles, beams.range_max)
        return beams

    def _deskew(self, t_s: float, beams: Beams, twist):
        """Each beam's laser motion over the sweep (None: a rigid scan: deskew off, or no sweep timing)."""
        if not (self.params.deskew and self.model.supports_deskew):
            return None
        return deskew_offsets(beams.times, t_s, twist, self.model.laser_offset)

    def _weigh(self, beams: Beams, offsets, t_s: float, gate: Gate):
        """The cloud's sensor update, resampled when due (not while holding: the cloud moved on odometry
        only), and its estimate; None: every particle impossible (the weights kept). The first update after
        an initial pose is tempered (``temper_next``, cleared once it succeeded)."""
        if not self.recovery.holding:
            self._weighed = (self.pf.num_particles, int(np.size(beams.ranges)))
            stages = self.params.initial_update_stages if self.temper_next else 1
            ok = self.pf.sensor_update(beams.ranges, beams.angles, offsets, beams.range_max, stages).ok
            self.temper_next = self.temper_next and not ok
            if not ok:
                self.impossible += 1
                return None
        self.impossible, self.t_update = 0, t_s
        self.policy.updated(gate.speed, gate.yaw_rate)
        return self.pf.estimate()

    def _apply(self, decision: Decision, t_s: float, update: Update | None = None) -> Used:
        """The one place a decision takes effect: the cloud, the counts, the range scale, the published
        estimate (the timeline's new anchor)."""
        action, estimate = decision.action, decision.estimate
        if action is Action.RESPREAD:
            self.recoveries += 1
            self.spread(t_s)
            return Used(action)
        if action is Action.UNDO:
            self.pf.restore(decision.cloud)
            self.refused_jumps += 1
        elif action is Action.SWITCH:
            self.pf.set_particles(decision.cloud.particles)
            self.recoveries += 1
        elif action is Action.CONVERGE:
            self.seeder.converged(self.pf, estimate.pose)
        if action in LEARNS and self.range_scale is not None:
            self._learn_range_scale(update, estimate)
        published = update.published if update is not None else None
        if published is None and (action is Action.SWITCH or self.glide.active):
            published = self.timeline.pose_at(t_s)  # the last published pose carried to t_s: a glide's start
        carried = None if published is None else published.pose
        if decision.glide:
            self.glide.start(carried, estimate.pose)
        if estimate is None and self.glide.active:  # no update: the glide goes on, the cloud moved on odometry
            estimate = self.pf.estimate()
        if estimate is None:
            return Used(action)
        pose, covariance = self.glide.apply(carried, estimate.pose, estimate.covariance)
        corrected = PoseEstimate(stamp=t_s, pose=pose, covariance=covariance)
        self.timeline.set_anchor(corrected)
        return Used(action, corrected)

    def _learn_range_scale(self, update: Update, estimate) -> None:
        """The range scale from a tracking update: its beams (deskewed as it deskewed them) against the
        ranges ray cast at its estimate (``core.localizer.range_scale``)."""
        beams = update.beams
        probe = self.model.range_probe(beams.angles, update.offsets, beams.range_max)

        def cast(poses):  # the probe's rays counted (``core.cost``: range_scale)
            self.cost.cast("range_scale", len(poses) * beams.ranges.size)
            return probe.cast(poses)
        if self.range_scale.update(beams.ranges, cast, estimate.pose, beams.range_min, probe.z_max, probe.reach,
                                   estimate.covariance, probe.wall_depth):
            self.model.set_range_scale(self.range_scale.scale)

    # ------------------------------------------------------------------ the map, the laser, (re)initialisation
    def set_map(self, occupancy_map: OccupancyMap) -> None:
        """A new map (the sensor model already has it): its range scale is learnt anew."""
        if self.range_scale is not None:
            self.range_scale.reset()
            self.model.set_range_scale(self.range_scale.scale)
        self.map = occupancy_map
        self.recovery.set_map(occupancy_map, self.model.laser_offset)

    def set_laser_offset(self, offset) -> None:
        self.model.set_laser_offset(offset)
        self.recovery.set_laser_offset(offset)

    def initialize(self, init: InitialPose, stamp: float | None) -> None:
        """A cloud around an initial pose, describing ``stamp``; its first update tempered."""
        self.pf.resize(self.params.num_particles)
        self.pf.hold_count(False)
        self.pf.initialize_gaussian(init.pose, init.covariance, init.std)
        self.restart(stamp, temper=True)

    def spread(self, stamp: float | None) -> None:
        """A global spread over the map's free space (``GlobalSeeder``), describing ``stamp``."""
        self.seeder.spread(self.pf, self.map)
        self.restart(stamp)

    def restart(self, stamp: float | None, temper: bool = False) -> None:
        """The particles were (re-)initialised and describe ``stamp`` (scan clock; the newest odometry's time
        if unusable); ``temper``: the first sensor update is tempered. Their estimate is the new anchor."""
        self.recovery.restart()
        self.glide.stop()
        self.policy.force()
        t = self.timeline.usable(stamp) if not self.timeline.empty else stamp
        self.restart_clock(t)
        self.temper_next = temper
        est = self.pf.estimate()
        t = t if t is not None and math.isfinite(t) else 0.0
        self.timeline.set_anchor(PoseEstimate(stamp=t, pose=est.pose, covariance=est.covariance))

    def restart_clock(self, t: float | None) -> None:
        """The filter's times move to t (an initialisation, or a new odometry history after a clock jump)."""
        self.t_filter = self.t_update = t
        self.impossible = 0
