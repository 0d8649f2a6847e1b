"""Recovery policy: tracking, or holding while the scans disagree with the map — never a jump.

After every sensor update the estimate x̂ is scored against the (downsampled) scan: the scan–map
agreement a ∈ [0, 1] (``health.AgreementScorer``: the share of valid beams ending within 0.10 m of an
occupied cell). ``health.HealthMonitor`` averages it (fast and slow) and calls the filter lost when
the fast average stays low for ``health_lost_updates`` updates. Then, with ``recovery`` on:

    hold       the cloud is kept and moves on odometry only (a scan the map cannot explain — moved
               furniture, a changed building — must not drag it); each scan still scores the estimate,
               and the fast average back above the lost floor resumes tracking
    search     every ``recovery_search_period`` s (scan clock) without a challenger, the global seeder
               proposes poses that fit the current scan (``filter.global_init.seed_from_scan``) and a
               small second cloud of ``recovery_particles`` — the challenger — starts there; it moves
               and is updated with the same odometry and scans as the main cloud
    switch     only when the converged challenger's agreement a_c beats the main estimate's a_e and is
               what this map and sensor normally score: a_c ≥ a_e + recovery_margin and
               a_c ≥ max(health_lost_floor, a_normal − recovery_margin), a_normal the highest slow average
               seen while tracking (what this map and sensor score when all is well), for
               ``recovery_confirm_updates`` updates in a row while the robot travelled
               ``recovery_confirm_distance`` m (a look-alike place rarely keeps fitting as the robot moves;
               a near miss re-locks the same way, a short move): the main cloud becomes the challenger's. A
               challenger that has not won within ``recovery_challenger_timeout`` s is dropped (the next
               search may try again)
    resume     the fast average back above the lost floor: tracking again
    glide      after a switch the cloud is the challenger's at once, but the published estimate
               moves there in steps (``SwitchGlide``): the odometry carries the last published pose x̄
               to the scan's time, and with d = x̂ ⊖ x̄ (the cloud's estimate minus it, θ wrapped)

                   x̄ ← x̄ + f·d,   f = min(1, recovery_switch_step / |d_xy|, recovery_switch_turn / |d_θ|)

               per sensor update, its covariance widened by the part still to go, (1 − f)² d dᵀ on the
               diagonal, until f = 1: a confirmed correction is never one jump of the published pose,
               however far (the glide is a correction, not a motion: its straight path may cross a wall,
               and the covariance says how far there is still to go). The glide goes on with every scan,
               the robot moving or not. ``recovery_switch_glide_max`` > 0 publishes a switch farther than
               that at once (a robot that may be carried elsewhere)
    jump       a tracking update (no switch) whose estimate x̂ lies more than ``recovery_jump_glide`` m from
               x̄ and more than JUMP_SIGMAS standard deviations of x̄'s position covariance Σ in the
               direction of the move (dᵀ Σ⁻¹ d > JUMP_SIGMAS², d = x̂ − x̄ in x, y: a cloud whose weight
               moved from one place to another after the map disagreed for a while) is a jump. It is
               kept only if the scan fits there clearly better than at x̄,

                   a(x̂) ≥ a(x̄) + recovery_margin,

               and then glides the same way; otherwise the update is undone (the cloud as before it,
               moved on odometry, one log line): one scan never moves the pose to a place that does not
               explain it better — after a hold, a cloud spread by odometry noise can otherwise collapse
               onto a look-alike pose half a metre and tens of degrees away from where odometry says

A global spread (start, service) is judged only once converged (cloud std < global_converged_std):
before that, its mean says nothing about any of its hypotheses. ``status`` is what the node reports.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from localization.core.geometry import wrap_angle
from localization.core.health import AgreementScorer, HealthMonitor, cloud_spread
from localization.core.occupancy_map import OccupancyMap

COV_FLOOR = 1e-12  # m²: added to the published position covariance before inverting it (a point cloud)
JUMP_SIGMAS = 3.0  # a tracking update's move beyond this many standard deviations of the published pose can jump

TRACKING, HOLDING = "tracking", "scans disagree with the map"


@dataclass(frozen=True)
class Judgement:
    converged: bool = False  # a global spread has just converged
    lost: bool = False  # the filter has just been judged lost (holding starts)
    agreement: float = math.nan  # of this update's estimate (NaN: not scored)
    message: str = ""  # what to log (empty: nothing)


class RecoveryPolicy:
    def __init__(self, params):
        self.params = params
        self.monitor = HealthMonitor.from_params(params)
        self._scorer: AgreementScorer | None = None
        self.holding = False  # lost: the scans disagree with the map around the estimate
        self.challenger = None  # a MonteCarloLocalizer started where the scan fits, or None
        self._challenger_since = -math.inf  # s, scan clock
        self._last_search = -math.inf  # s, scan clock
        self._wins = 0  # updates in a row the challenger explained the scan clearly better
        self._won_distance = 0.0  # m travelled during those updates
        self._normal = math.nan  # the highest slow average agreement seen while tracking

    health = property(lambda self: self.monitor.health)
    status = property(lambda self: HOLDING if self.holding else TRACKING)

    def set_map(self, occupancy_map: OccupancyMap, laser_offset) -> None:
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
        return self._scorer.score(pose, *beams)

    def judge(self, pose, covariance, beams, global_mode: bool) -> Judgement:
        p = self.params
        converged = False
        if global_mode:
            if cloud_spread(covariance) >= p.global_converged_std:
                return Judgement()  # still spread
            converged = True
            self.restart()
        agreement = self.score(pose, beams)
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

    def search_due(self, t: float) -> bool:
        """Start a challenger now? (holding, none running, the last search long enough ago)"""
        return self.holding and self.challenger is None and t - self._last_search >= self.params.recovery_search_period

    def start(self, challenger, t: float) -> None:
        self.challenger, self._challenger_since, self._last_search = challenger, t, t
        self._wins, self._won_distance = 0, 0.0

    def challenge(self, main_agreement: float, beams, t: float, distance: float) -> str:
        """After the challenger's own update (``distance``: m travelled since the previous update):
        "switch", "drop" or "" (keep watching)."""
        p, c = self.params, self.challenger
        est = c.estimate()
        a_c = self.score(est.pose, beams) if cloud_spread(est.covariance) < p.global_converged_std else math.nan
        normal = self._normal - p.recovery_margin if math.isfinite(self._normal) else 0.0
        better = (math.isfinite(a_c) and a_c >= max(p.health_lost_floor, normal)
                  and a_c >= (main_agreement if math.isfinite(main_agreement) else 0.0) + p.recovery_margin)
        self._wins = self._wins + 1 if better else 0
        self._won_distance = self._won_distance + distance if better else 0.0
        if self._wins >= p.recovery_confirm_updates and self._won_distance >= p.recovery_confirm_distance:
            return "switch"
        if t - self._challenger_since > p.recovery_challenger_timeout:
            self.challenger, self._wins = None, 0
            return "drop"
        return ""


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
    """The published estimate's way to a place a challenger won (module doc, "glide")."""

    def __init__(self, step: float, turn: float, farthest: float):
        self.step, self.turn = float(step), float(turn)  # m, rad per sensor update (0: at once)
        self.farthest = float(farthest)  # m: a switch farther than this is published at once (0: none)
        self.active = False

    def start(self, published, pose) -> None:
        """A switch from the ``published`` pose (carried to the switch's time; None: none) to ``pose``."""
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
