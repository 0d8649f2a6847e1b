"""Recovery policy: after each sensor update, is the filter converged, tracking, or lost?

After every sensor update the estimate x̂ is scored against the (downsampled) scan: the scan–map
agreement a ∈ [0, 1] (``health.AgreementScorer``: the share of valid beams ending within 0.10 m of
an occupied cell). ``health.HealthMonitor`` averages it (fast and slow) and calls the filter lost
when the fast average stays low. The policy then decides:

    spread cloud (global mode)   converged once the position std < global_converged_std:
                                 the cloud shrinks back to num_particles, the monitor restarts
    lost and recovery on         re-spread globally (the global seeder proposes the poses)
    otherwise                    keep tracking

``judge`` returns the decision; the localizer carries it out. The monitor only judges a converged
cloud (the mean of many hypotheses says nothing about any of them).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from localization.core.health import AgreementScorer, HealthMonitor, cloud_spread
from localization.core.occupancy_map import OccupancyMap


@dataclass(frozen=True)
class Judgement:
    converged: bool = False  # a global spread has just converged
    lost: bool = False  # the filter is lost and recovery should re-spread it
    agreement: float = math.nan  # of this update's estimate (NaN: not scored)
    message: str = ""  # what to log (empty: nothing)


class RecoveryPolicy:
    def __init__(self, params):
        self.params = params
        self.monitor = HealthMonitor.from_params(params)
        self._scorer: AgreementScorer | None = None

    @property
    def health(self) -> float:
        return self.monitor.health

    def set_map(self, occupancy_map: OccupancyMap, laser_offset) -> None:
        self._scorer = AgreementScorer(occupancy_map, laser_offset, range_scale=self.params.lidar_scale_to_map_scale)
        self.monitor.reset()

    def set_laser_offset(self, laser_offset) -> None:
        if self._scorer is not None:
            self._scorer.laser_offset = np.asarray(laser_offset, dtype=float).reshape(3).copy()

    def restart(self) -> None:
        """After an initialisation: the fast average starts again, the long-term one is kept."""
        self.monitor.reset(keep_slow=True)

    def judge(self, pose, covariance, ranges, angles, range_min: float, range_max: float,
              global_mode: bool) -> Judgement:
        p = self.params
        converged = False
        if global_mode:
            if cloud_spread(covariance) >= p.global_converged_std:
                return Judgement()  # still spread
            converged = True
            self.restart()
        agreement = self._scorer.score(pose, ranges, angles, range_min, range_max)
        lost = self.monitor.update(agreement) and p.recovery
        message = ""
        if lost:
            m = self.monitor
            message = (f"localization lost: scan-map agreement {m.fast:.2f} (long-term {m.slow:.2f}) for "
                       f"{m.low_count} updates; re-spreading the particles over the free space (recovery)")
        return Judgement(converged=converged, lost=lost, agreement=agreement, message=message)
