"""Filter health: is the estimate still where the scans say it is? (numpy only, no ROS)

Two pieces:

- ``AgreementScorer``: the scan–map agreement of one pose — the fraction of valid beams whose
  endpoint lies within ``tolerance`` (0.10 m) of an occupied map cell. It is also the truth-free
  quality figure of ``localization.metrics`` (which re-exports it from here). One compiled pass over
  the beams (``agreement_kernel``); ``score_numpy`` is its numpy reference.
- ``HealthMonitor``: after every sensor update the Localizer scores the estimate against the
  (downsampled) scan and feeds the agreement ``a_k`` to two exponential moving averages, as in
  augmented MCL (Thrun, Burgard, Fox, *Probabilistic Robotics*, table 8.3) but on the agreement
  rather than on the raw likelihood (whose scale depends on the beam count and squash factor)::

      fast_k = fast_{k-1} + α_fast (a_k − fast_{k-1})        α_fast ≈ 0.2  (a few updates)
      slow_k = slow_{k-1} + α_slow (a_k − slow_{k-1})        α_slow ≈ 0.02 (seconds)

  The filter is *lost* when, for ``lost_updates`` sensor updates in a row, ``fast`` is below
  the absolute ``lost_floor`` or below ``lost_ratio · slow`` (a sudden drop from what this
  environment normally scores). ``health`` (published on ``/pf/health``) is ``fast`` in [0, 1].

  The monitor only judges a *converged* cloud: while particles are still spread (global
  localization, recovery), the estimate is a mean over many hypotheses and its agreement says
  nothing; the Localizer calls ``reset()`` after every (re-)initialisation.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from localization.core.geometry import compose

try:  # one compiled pass over the beams when numba is there (pinned); the numpy reference otherwise
    from numba import njit
except ImportError:  # pragma: no cover
    njit = None
from localization.core.occupancy_map import OccupancyMap
from localization.core.parameters import default

AGREEMENT_TOLERANCE_M = 0.10


class AgreementScorer:
    """Scan–map agreement of scans against one map (caches the distance field)."""

    def __init__(self, occupancy_map: OccupancyMap, laser_offset=(0.0, 0.0, 0.0),
                 tolerance: float = AGREEMENT_TOLERANCE_M, range_scale: float = 1.0):
        self.map = occupancy_map
        self.laser_offset = np.asarray(laser_offset, dtype=float).reshape(3)
        self.range_scale = float(range_scale)  # lidar metres -> map metres (lidar_scale_to_map_scale)
        self.tolerance = float(tolerance)
        # cell-centre distances, so "within tolerance" of a wall means within tolerance + half a cell
        self.near = occupancy_map.near_obstacle(self.tolerance + 0.5 * occupancy_map.resolution)

    def endpoints(self, base_pose, ranges, angles, range_min: float, range_max: float) -> np.ndarray:
        """World xy (K, 2) of the valid beams' endpoints seen from ``base_pose``."""
        r = np.asarray(ranges, dtype=float).ravel()
        a = np.asarray(angles, dtype=float).ravel()
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(r) & (r >= range_min) & (r < range_max)
        laser = compose(np.asarray(base_pose, dtype=float), self.laser_offset)
        th = laser[2] + a[valid]
        r = r[valid] * self.range_scale
        return np.column_stack([laser[0] + r * np.cos(th), laser[1] + r * np.sin(th)])

    def score(self, base_pose, ranges, angles, range_min: float, range_max: float) -> float:
        """Fraction of valid beams ending within ``tolerance`` of an occupied cell (NaN: none valid)."""
        if agreement_kernel is None:
            return self.score_numpy(base_pose, ranges, angles, range_min, range_max)
        laser = compose(np.asarray(base_pose, dtype=float), self.laser_offset)
        ox, oy, yaw = self.map.origin
        hits, valid = agreement_kernel(float(laser[0]), float(laser[1]), float(laser[2]),
                                       np.ascontiguousarray(ranges, dtype=float).ravel(),
                                       np.ascontiguousarray(angles, dtype=float).ravel(), float(range_min),
                                       float(range_max), self.range_scale, float(ox), float(oy), math.cos(yaw),
                                       math.sin(yaw), float(self.map.resolution), self.near)
        return hits / valid if valid else math.nan

    def score_numpy(self, base_pose, ranges, angles, range_min: float, range_max: float) -> float:
        """``score`` in numpy: the reference of ``agreement_kernel``."""
        pts = self.endpoints(base_pose, ranges, angles, range_min, range_max)
        if len(pts) == 0:
            return math.nan
        return float(np.count_nonzero(self.map.lookup(pts, self.near)) / len(pts))


if njit is not None:
    @njit(cache=True, nogil=True)
    def agreement_kernel(lx, ly, lth, ranges, angles, range_min, range_max, scale, map_ox, map_oy, map_c, map_s,
                         resolution, near):  # pragma: no cover - compiled
        """(beams ending in a ``near`` cell, valid beams) for the laser at (lx, ly, lth): as
        ``AgreementScorer.endpoints`` and ``OccupancyMap.lookup`` (off the map: not near)."""
        h, w = near.shape
        hits = 0
        valid = 0
        for b in range(ranges.size):
            r = ranges[b]
            if not (math.isfinite(r) and r >= range_min and r < range_max):
                continue
            valid += 1
            th = lth + angles[b]
            r = r * scale
            dx = lx + r * math.cos(th) - map_ox
            dy = ly + r * math.sin(th) - map_oy
            gx = (map_c * dx + map_s * dy) / resolution
            gy = (-map_s * dx + map_c * dy) / resolution
            if not (math.isfinite(gx) and math.isfinite(gy)):
                continue
            col = int(math.floor(gx))
            row = int(math.floor(gy))
            if 0 <= col < w and 0 <= row < h and near[row, col]:
                hits += 1
        return hits, valid
else:  # pragma: no cover
    agreement_kernel = None


@dataclass
class HealthMonitor:
    """Fast/slow moving averages of the scan–map agreement and the ``lost`` decision."""

    fast_alpha: float = default("health_fast_alpha")
    slow_alpha: float = default("health_slow_alpha")
    lost_floor: float = default("health_lost_floor")
    lost_ratio: float = default("health_lost_ratio")
    lost_updates: int = default("health_lost_updates")

    def __post_init__(self):
        self.reset()

    @classmethod
    def from_params(cls, params) -> "HealthMonitor":
        return cls(params.health_fast_alpha, params.health_slow_alpha, params.health_lost_floor,
                   params.health_lost_ratio, params.health_lost_updates)

    def reset(self, keep_slow: bool = False) -> None:
        """Forget the history (after an initialisation): the next agreement starts the fast
        average. ``keep_slow``: keep the long-term average (what this map and sensor normally
        score), so a cloud that re-converges to a wrong place is still judged against it; without
        one, the next agreement starts it too."""
        self.fast = math.nan
        if not (keep_slow and math.isfinite(getattr(self, "slow", math.nan))):
            self.slow = math.nan
        self.low_count = 0
        self.samples = 0

    @property
    def health(self) -> float:
        """The fast average in [0, 1]; NaN before the first sample."""
        return self.fast

    def update(self, agreement: float) -> bool:
        """Feed one agreement value (NaN: no valid beam, ignored); returns True when lost."""
        if not math.isfinite(agreement):
            return False
        a = min(max(float(agreement), 0.0), 1.0)
        if self.samples == 0:
            self.fast = a
            self.slow = a if math.isnan(self.slow) else self.slow + self.slow_alpha * (a - self.slow)
        else:
            self.fast += self.fast_alpha * (a - self.fast)
            self.slow += self.slow_alpha * (a - self.slow)
        self.samples += 1
        low = self.fast < self.lost_floor or self.fast < self.lost_ratio * self.slow
        self.low_count = self.low_count + 1 if low else 0
        return self.low_count >= self.lost_updates


def cloud_spread(covariance) -> float:
    """Position spread (m) of a particle cloud: sqrt of the largest eigenvalue of the xy covariance
    (symmetrised), in closed form on Python floats: (a + d)/2 + hypot((a − d)/2, b). It equals
    ``cloud_spread_numpy`` (LAPACK's eigvalsh) to rounding; a scan makes one call, where numpy's
    eigvalsh costs tens of microseconds."""
    (a, b0), (b1, d) = (row[:2] for row in np.asarray(covariance, dtype=float)[:2].tolist())
    if not all(math.isfinite(v) for v in (a, b0, b1, d)):
        return math.inf
    largest = 0.5 * (a + d) + math.hypot(0.5 * (a - d), 0.5 * (b0 + b1))
    return math.sqrt(max(largest, 0.0))


def cloud_spread_numpy(covariance) -> float:
    """``cloud_spread`` by numpy's eigvalsh: its reference."""
    cov = np.asarray(covariance, dtype=float)[:2, :2]
    if not np.all(np.isfinite(cov)):
        return math.inf
    return float(math.sqrt(max(np.linalg.eigvalsh(0.5 * (cov + cov.T))[-1], 0.0)))
