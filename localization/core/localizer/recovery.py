"""Recovery: the one owner of what a sensor update leads to. ``Recovery.decide`` takes the update's result
(``Update``) and returns one ``Decision``; the pipeline applies it in one place.

After every sensor update the estimate x̂ is scored against the (downsampled) scan: the scan–map
agreement a ∈ [0, 1] (``health.AgreementScorer``: the share of valid beams ending within 0.10 m of an
occupied cell). ``health.HealthMonitor`` averages it (fast and slow) and calls the filter lost when
the fast average stays low for ``health_lost_updates`` updates. The decisions, in the order they are
taken:

    re-spread  every particle impossible for ``max_impossible_scans`` scans in a row: spread over the
               free space (fewer: the weights are kept, the update skipped)
    undo       a tracking update (no switch) whose estimate x̂ lies more than ``recovery_jump_glide`` m from
               the published pose x̄ carried to the scan's time and more than JUMP_SIGMAS standard
               deviations of x̄'s position covariance Σ in the direction of the move (dᵀ Σ⁻¹ d > JUMP_SIGMAS²,
               d = x̂ − x̄ in x, y: ``is_jump``) is a jump. It is kept only if the scan fits there clearly
               better, a(x̂) ≥ a(x̄) + recovery_margin, and then published in steps (the glide below);
               otherwise the update is undone: the cloud as before it, moved on odometry. One scan never
               moves the pose to a place that does not explain it better
    spread     a global spread (start, service) is judged only once converged (cloud std <
               global_converged_std): before that its mean says nothing about any of its hypotheses;
               converge: it has, the cloud goes back to num_particles
    hold       lost (with ``recovery`` on): the cloud moves on odometry only (a scan the map cannot
               explain — moved furniture, a changed building — must not drag it); each scan still scores
               the estimate, and the fast average back above the lost floor resumes tracking
    switch     while holding, every ``recovery_search_period`` s (scan clock) without a challenger, the
               global seeder proposes poses that fit the current scan and a small second cloud of
               ``recovery_particles`` — the challenger — starts there; it moves and is updated with the
               same odometry and scans. It wins when converged and its agreement a_c beats the main
               estimate's a_e and is what this map and sensor normally score,
                   a_c ≥ a_e + recovery_margin  and  a_c ≥ max(health_lost_floor, a_normal − recovery_margin)
               (a_normal the highest slow average seen while tracking) for ``recovery_confirm_updates``
               updates in a row over ``recovery_confirm_distance`` m (a look-alike place rarely keeps
               fitting as the robot moves): the cloud becomes the challenger's. A challenger that has not
               won within ``recovery_challenger_timeout`` s is dropped
    track      otherwise: the update stands

A switch and a kept jump are published in steps (``SwitchGlide``): the odometry carries the last
published pose x̄ to the scan's time, and with d = x̂ ⊖ x̄ (θ wrapped)

    x̄ ← x̄ + f·d,   f = min(1, recovery_switch_step / |d_xy|, recovery_switch_turn / |d_θ|)

per scan, the covariance widened by (1 − f)² d dᵀ on the diagonal, until f = 1. The glide is a
correction, not a motion (its straight path may cross a wall); it goes on with every scan, the robot
moving or not. ``recovery_switch_glide_max`` > 0 publishes a switch farther than that at once.
``status`` is what the node reports.
"""
from __future__ import annotations

import enum
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from localization.core.cost import CostMeter
from localization.core.filter.mcl import ESTIMATE_PASSES, Estimate, Snapshot
from localization.core.geometry import wrap_angle
from localization.core.localizer.health import AgreementScorer, HealthMonitor, cloud_spread
from localization.core.localizer.timeline import PoseEstimate
from localization.core.occupancy_map import OccupancyMap

COV_FLOOR = 1e-12  # m²: added to the published position covariance before inverting it (a point cloud)
JUMP_SIGMAS = 3.0  # a tracking update's move beyond this many standard deviations of the published pose can jump

TRACKING, HOLDING = "tracking", "scans disagree with the map"


class Action(enum.Enum):
    """What a scan does to the cloud (module docstring)."""

    SKIP = "skip"  # no sensor update: not due, no valid beam, or every particle impossible (weights kept)
    TRACK = "track"  # the update stands
    UNDO = "undo"  # the update jumped to a place the scan fits no clearly better: the cloud as before it
    HOLD = "hold"  # the scans disagree with the map: the cloud moves on odometry only
    SWITCH = "switch"  # the challenger won: the cloud becomes the challenger's
    RESPREAD = "re-spread"  # every particle impossible, scan after scan: spread over the free space
    SPREAD = "spread"  # a global spread, not yet converged
    CONVERGE = "converge"  # a global spread has converged: back to num_particles


@dataclass(frozen=True)
class Decision:
    """The one value ``Recovery.decide`` returns for a scan."""

    action: Action
    estimate: Estimate | None = None  # the cloud's estimate once the action is applied (None: SKIP, RESPREAD)
    glide: bool = False  # published in steps toward ``estimate`` (a switch, or an update kept though it jumped)
    cloud: Snapshot | None = None  # UNDO: the cloud before the update; SWITCH: the challenger's


@dataclass(frozen=True)
class Beams:
    """The beams of a scan a sensor update uses, in the laser frame, and the scan's range limits."""

    ranges: np.ndarray  # m (inf: no return)
    angles: np.ndarray  # rad
    indices: np.ndarray  # which beams of the full scan
    range_min: float  # m
    range_max: float  # m
    times: np.ndarray | None = None  # s, scan clock: each beam's own time (None: no sweep timing)

    @property
    def scored(self) -> tuple:
        """(ranges, angles, range_min, range_max): what the agreement scores."""
        return self.ranges, self.angles, self.range_min, self.range_max


@dataclass(frozen=True)
class Update:
    """A scan's sensor update, as the recovery decides on it."""

    time: float  # s, scan clock
    beams: Beams  # the beams the update used
    offsets: np.ndarray | None  # (B, 3) their deskew offsets (None: a rigid scan)
    travelled: float  # m since the previous sensor update
    global_mode: bool  # a global spread, not yet converged, before this update
    estimate: Estimate | None  # the cloud's after the update (holding: moved on odometry only); None: impossible
    impossible: int  # scans in a row that made every particle impossible
    before: Snapshot | None = None  # the cloud before the update, when its move is judged (a jump)
    published: PoseEstimate | None = None  # the published pose carried to ``time``, when the move is judged


@dataclass(frozen=True)
class Judgement:
    converged: bool = False  # a global spread has just converged
    lost: bool = False  # the filter has just been judged lost (holding starts)
    agreement: float = math.nan  # of this update's estimate (NaN: not scored)
    message: str = ""  # what to log (empty: nothing)


class Recovery:
    """``challenger(occupancy_map, ranges, angles, range_max)`` starts a challenger cloud (the global
    seeder's); ``warn(key, message)`` logs one throttled line."""

    def __init__(self, params, challenger: Callable, warn):
        self.params, self.warn = params, warn
        self._new_challenger = challenger
        self.monitor = HealthMonitor.from_params(params)
        self._scorer: AgreementScorer | None = None
        self._map: OccupancyMap | None = None
        self.holding = False  # lost: the scans disagree with the map around the estimate
        self.challenger = None  # a MonteCarloLocalizer started where the scan fits, or None
        self._challenger_since = -math.inf  # s, scan clock
        self._last_search = -math.inf  # s, scan clock
        self._wins = 0  # updates in a row the challenger explained the scan clearly better
        self._won_distance = 0.0  # m travelled during those updates
        self._normal = math.nan  # the highest slow average agreement seen while tracking
        self.cost = CostMeter()  # the agreement's beams (``core.cost``; the pipeline shares its meter)

    health = property(lambda self: self.monitor.health)
    status = property(lambda self: HOLDING if self.holding else TRACKING)

    def set_map(self, occupancy_map: OccupancyMap, laser_offset) -> None:
        self._map = occupancy_map
        self._scorer = AgreementScorer(occupancy_map, laser_offset, range_scale=self.params.lidar_scale_to_map_scale)
        self.monitor.reset()
        self._stop_holding()

    def set_laser_offset(self, laser_offset) -> None:
        if self._scorer is not None:
            self._scorer.laser_offset = np.asarray(laser_offset, dtype=float).reshape(3).copy()

    def restart(self) -> None:
        """After an initialisation: the fast average starts again, the long-term one is kept."""
        self.monitor.reset(keep_slow=True)
        self._stop_holding()

    def _stop_holding(self) -> None:
        self.holding, self.challenger, self._wins, self._won_distance = False, None, 0, 0.0

    def score(self, pose, beams) -> float:
        """Scan–map agreement of a pose; ``beams`` = (ranges, angles, range_min, range_max)."""
        self.cost.cast("agreement", np.size(beams[0]))
        return self._scorer.score(pose, *beams)

    # ------------------------------------------------------------------ the decision
    def decide(self, u: Update) -> Decision:
        """The one decision for a scan's sensor update (module docstring, in that order)."""
        p = self.params
        if u.estimate is None:  # every particle impossible: the weights were kept
            if u.impossible < p.max_impossible_scans:
                self.warn("scan-degenerate", "every particle has likelihood 0 for this scan: weights kept")
                return Decision(Action.SKIP)
            self.warn("scan-impossible", f"{u.impossible} scans in a row gave every particle likelihood 0 (all "
                      "off the map or in walls): re-spreading particles over the free space")
            return Decision(Action.RESPREAD)
        estimate, undone, jumped = u.estimate, False, False
        if u.before is not None and is_jump(u.published, estimate.pose, p.recovery_jump_glide):
            undone = self._refuses(u.published.pose, estimate.pose, u.beams.scored)
            jumped = not undone
            if undone:
                self.cost.sweep("estimate", ESTIMATE_PASSES)
            estimate = u.before.estimate() if undone else estimate
        verdict = self._judge(estimate, u.beams.scored, u.global_mode)
        if verdict.message:
            self.warn("recovery-lost" if verdict.lost else "recovery-back", verdict.message)
        switched = self._challenge(u, verdict.agreement)
        if switched is not None:
            return Decision(Action.SWITCH, switched.estimate(), glide=True, cloud=Snapshot(switched.particles,
                                                                                           switched.log_weights))
        if undone:
            return Decision(Action.UNDO, estimate, cloud=u.before)
        if u.global_mode:
            return Decision(Action.CONVERGE if verdict.converged else Action.SPREAD, estimate)
        return Decision(Action.HOLD if self.holding else Action.TRACK, estimate, glide=jumped)

    def _refuses(self, published, pose, beams) -> bool:
        """Does the scan fit ``pose`` (an update's jump) no clearly better than the ``published`` pose?"""
        moved, kept = self.score(pose, beams), self.score(published, beams)
        if not moved < kept + self.params.recovery_margin:
            return False
        self.warn("jump-refused", f"a sensor update moved the estimate {math.dist(pose[:2], published[:2]):.2f} m "
                  f"to a place the scan fits no clearly better (agreement {moved:.2f}, {kept:.2f} at the published "
                  "pose): update undone, the pose moves on odometry")
        return True

    def _judge(self, estimate: Estimate, beams, global_mode: bool) -> Judgement:
        """Converged / lost / back to tracking, from the estimate's agreement."""
        p = self.params
        converged = False
        if global_mode:
            if cloud_spread(estimate.covariance) >= p.global_converged_std:
                return Judgement()  # still spread
            converged = True
            self.restart()
        agreement = self.score(estimate.pose, beams)
        lost = self.monitor.update(agreement) and p.recovery and not self.holding
        if not self.holding and math.isfinite(self.monitor.slow) and self.monitor.samples >= p.health_lost_updates:
            self._normal = max(self.monitor.slow, self._normal) if math.isfinite(self._normal) else self.monitor.slow
        message = ""
        if lost:
            m = self.monitor
            self.holding = True
            message = (f"localization lost: scan-map agreement {m.fast:.2f} (long-term {m.slow:.2f}) for "
                       f"{m.low_count} updates: holding the pose on odometry (the scans no longer move it), "
                       "searching the map for a place they fit")
        elif self.holding and self.monitor.low_count == 0:
            self._stop_holding()
            message = f"scans agree with the map again (agreement {self.monitor.fast:.2f}): tracking"
        return Judgement(converged=converged, lost=lost, agreement=agreement, message=message)

    # ------------------------------------------------------------------ the challenger
    def _challenge(self, u: Update, main_agreement: float):
        """While holding: start, update and judge a challenger; the challenger when it wins (None: no switch)."""
        p = self.params
        if self.holding and self.challenger is None and u.time - self._last_search >= p.recovery_search_period:
            self.challenger = self._new_challenger(self._map, u.beams.ranges, u.beams.angles, u.beams.range_max)
            self._challenger_since = self._last_search = u.time
            self._wins, self._won_distance = 0, 0.0
            return None  # its first update is the next scan's
        c = self.challenger
        if c is None:
            return None
        c.sensor_update(u.beams.ranges, u.beams.angles, u.offsets, range_max=u.beams.range_max)
        est = c.estimate()
        converged = cloud_spread(est.covariance) < p.global_converged_std
        a_c = self.score(est.pose, u.beams.scored) if converged else math.nan
        normal = self._normal - p.recovery_margin if math.isfinite(self._normal) else 0.0
        better = (math.isfinite(a_c) and a_c >= max(p.health_lost_floor, normal)
                  and a_c >= (main_agreement if math.isfinite(main_agreement) else 0.0) + p.recovery_margin)
        self._wins = self._wins + 1 if better else 0
        self._won_distance = self._won_distance + u.travelled if better else 0.0
        if self._wins >= p.recovery_confirm_updates and self._won_distance >= p.recovery_confirm_distance:
            self.restart()
            self.warn("recovery-switch", f"recovery: the scans fit ({est.pose[0]:.2f}, {est.pose[1]:.2f}) clearly "
                      f"better for {p.recovery_confirm_updates}+ updates over {p.recovery_confirm_distance} m: "
                      "the cloud moves there")
            return c
        if u.time - self._challenger_since > p.recovery_challenger_timeout:
            self.challenger, self._wins = None, 0
        return None


def is_jump(published, pose, jump: float) -> bool:
    """Does a tracking update that moves the estimate from the ``published`` estimate (a PoseEstimate
    carried to the update's time; None: none) to ``pose`` jump? Farther than ``jump`` m (0: never) and
    outside ``JUMP_SIGMAS`` standard deviations of the published position in the direction of the move,
    d = x̂_xy − x̄_xy with dᵀ Σ_xy⁻¹ d > JUMP_SIGMAS² (a cloud converging from a wide initial pose moves
    within its own spread: no jump; a cloud spread along its track by a hold does not make a sideways
    move its own)."""
    if jump <= 0.0 or published is None:
        return False
    d = np.asarray(pose[:2], dtype=float) - np.asarray(published.pose[:2], dtype=float)
    if math.hypot(d[0], d[1]) <= jump:
        return False
    cov = np.asarray(published.covariance, dtype=float)[:2, :2] + COV_FLOOR * np.eye(2)
    return float(d @ np.linalg.solve(cov, d)) > JUMP_SIGMAS ** 2


class SwitchGlide:
    """The published estimate's way to a place a switch or a kept jump moved the cloud (module doc)."""

    def __init__(self, step: float, turn: float, farthest: float):
        self.step, self.turn = float(step), float(turn)  # m, rad per sensor update (0: at once)
        self.farthest = float(farthest)  # m: a switch farther than this is published at once (0: none)
        self.active = False

    def start(self, published, pose) -> None:
        """A glide from the ``published`` pose (carried to the switch's time; None: none) to ``pose``."""
        far = published is None or (self.farthest > 0 and
                                    math.hypot(pose[0] - published[0], pose[1] - published[1]) > self.farthest)
        self.active = self.step > 0 and self.turn > 0 and not far

    def stop(self) -> None:
        self.active = False

    def apply(self, published, pose, covariance) -> tuple[np.ndarray, np.ndarray]:
        """(pose, covariance) to publish for the cloud's ``pose``, given the last ``published`` pose
        carried to the same time (None: nothing published yet: the cloud's pose as it is)."""
        pose, covariance = np.asarray(pose, dtype=float), np.asarray(covariance, dtype=float)
        if not self.active or published is None:
            self.active = False
            return pose, covariance
        d = pose - np.asarray(published, dtype=float)
        d[2] = float(wrap_angle(d[2]))
        dist, turn = math.hypot(d[0], d[1]), abs(d[2])
        f = min(1.0, self.step / dist if dist > 0 else 1.0, self.turn / turn if turn > 0 else 1.0)
        if f >= 1.0:
            self.active = False
            return pose, covariance
        out = np.asarray(published, dtype=float) + f * d
        out[2] = float(wrap_angle(out[2]))
        return out, covariance + np.diag(((1.0 - f) * d) ** 2)
