"""Online estimate of the lidar-to-map range scale (``range_scale_estimation``).

The beam model scores a return z (lidar metres) as s·z − o map metres against the range d ray cast in
the map (s = ``lidar_scale_to_map_scale``, o = ``map_wall_depth``). When the building is a little
larger or smaller than its map (or the lidar's range calibration is off), every return is a fixed
factor too long or too short, and the best fit of the beam model moves along the corridor: walls ahead
read farther, so the estimate falls behind the car. This estimator follows that factor while the filter
tracks, from the beams of each sensor update seen from the estimate x̂:

    d_b  = the range ray cast at x̂ (map metres; beam b from its own, deskewed, laser pose)
    beam b is used when   r_min < z_b < r_max − RANGE_MARGIN_M,   d_b < reach − RANGE_MARGIN_M
                          and  |s·z_b − o − d_b| ≤ GATE_M + GATE_FRACTION · d_b
    ŝ    = Σ z_b (d_b + o) / Σ z_b²            least squares of d + o = ŝ·z through the origin
           (the gate is then re-centred on ŝ and ŝ computed again, once)
    s   ← s + α (clip(ŝ, s₀ (1 − β), s₀ (1 + β)) − s)

s₀ is the configured ``lidar_scale_to_map_scale`` (the start value and the centre of the bounds),
α = ``range_scale_alpha`` (per sensor update: a time constant of 1/α updates), β = ``range_scale_bound``.
reach is the farthest range the model casts (its table's, 10 m by default). A scan counts only when at
least ``MIN_BEAM_FRACTION`` of its beams (and ``MIN_BEAMS``) pass the gate and the cloud has converged
(largest position standard deviation ≤ ``MAX_SPREAD_M``); the Localizer feeds it only while tracking
(not during a global spread, not while holding the pose after "scans disagree with the map", not on a
scan after which the cloud moved to a challenger).

Why it is unbiased enough to use: Σ z·d / Σ z² weighs each beam by z², so the long beams, where a
scale error shows most and a pose error of a few centimetres least, dominate. Returns shorter than the
map says (furniture, people: unmapped obstacles) and longer ones (glass, open doors) fail the gate
unless they lie within a few centimetres of a mapped wall. A pose error along a corridor makes the
ranges ahead shorter and the ones behind longer, and the corridor's width (the side walls, which no
translation along it changes) pins the scale: the filter's estimate and the scale settle together.

``estimate_scale`` is the per-scan ŝ (vectorised numpy over the beams); ``RangeScaleEstimator`` keeps s.
Measured effects (simulated perturbed worlds, the real bags) are in docs/models.md.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from localization.core.health import cloud_spread

__all__ = ["GATE_FRACTION", "GATE_M", "MAX_SPREAD_M", "MIN_BEAMS", "MIN_BEAM_FRACTION", "RANGE_MARGIN_M",
           "RangeScaleEstimator", "estimate_scale"]

GATE_M = 0.10  # m: a beam is used when s·z − o lies within GATE_M + GATE_FRACTION · d of d ...
GATE_FRACTION = 0.02  # ... (0.3 m at 10 m: room for a 2 % scale error before the first estimate)
RANGE_MARGIN_M = 0.25  # m: beams this close to the lidar's range_max or the model's reach are not used
MIN_BEAMS = 10  # a scan counts with at least this many beams in the gate ...
MIN_BEAM_FRACTION = 0.25  # ... and at least this fraction of the scan's beams
MAX_SPREAD_M = 0.15  # m: ... and the cloud's largest position standard deviation at most this


def estimate_scale(z, d, scale: float, wall_depth: float = 0.0) -> tuple[float, int]:
    """(ŝ, beams used) of one scan: measured ranges ``z`` (lidar metres) against ranges ``d`` ray cast at
    the estimate (map metres), beams already limited to valid ones (finite, inside the lidar's and the
    model's reach). The gate is centred on ``scale`` first, then on the first ŝ (module docstring).
    (NaN, 0) when no beam passes."""
    z = np.asarray(z, dtype=float).ravel()
    d = np.asarray(d, dtype=float).ravel() + wall_depth  # the model's o moved to the map side: d + o = s·z
    tolerance = GATE_M + GATE_FRACTION * d
    s, used = math.nan, 0
    centre = float(scale)
    for _ in range(2):
        with np.errstate(invalid="ignore"):
            ok = np.abs(centre * z - d) <= tolerance
        used = int(np.count_nonzero(ok))
        if used == 0:
            return math.nan, 0
        zz = z[ok]
        s = float(np.dot(zz, d[ok]) / np.dot(zz, zz))
        centre = s
    return s, used


@dataclass
class RangeScaleEstimator:
    """The slowly filtered lidar-to-map range scale s (module docstring)."""

    prior: float = 1.0  # s₀: lidar_scale_to_map_scale as configured
    alpha: float = 0.02  # weight of each scan's ŝ (range_scale_alpha)
    bound: float = 0.05  # s stays within s₀ (1 ± bound) (range_scale_bound)

    def __post_init__(self):
        self.scale = float(self.prior)
        self.updates = 0  # scans that moved s

    @classmethod
    def from_parameters(cls, params) -> "RangeScaleEstimator":
        return cls(params.lidar_scale_to_map_scale, params.range_scale_alpha, params.range_scale_bound)

    def reset(self) -> None:
        """Back to s₀ (a new map)."""
        self.scale, self.updates = float(self.prior), 0

    @property
    def limits(self) -> tuple[float, float]:
        return self.prior * (1.0 - self.bound), self.prior * (1.0 + self.bound)

    def update(self, z, d, range_min: float, range_max: float, reach: float, covariance=None,
               wall_depth: float = 0.0) -> bool:
        """One scan: measured ranges ``z`` (lidar metres, NaN/inf for no return) and ranges ``d`` ray cast
        at the estimate (map metres, the same beams), the scan's ``range_min``/``range_max``, the model's
        ``reach`` (map metres), the cloud's ``covariance`` (3, 3) (None: not checked). True when s moved."""
        if covariance is not None and not cloud_spread(covariance) <= MAX_SPREAD_M:
            return False
        z = np.asarray(z, dtype=float).ravel()
        d = np.asarray(d, dtype=float).ravel()
        with np.errstate(invalid="ignore"):
            valid = (np.isfinite(z) & np.isfinite(d) & (z > range_min) & (z < range_max - RANGE_MARGIN_M)
                     & (d > 0.0) & (d < reach - RANGE_MARGIN_M))
        if np.count_nonzero(valid) < MIN_BEAMS:
            return False
        s, used = estimate_scale(z[valid], d[valid], self.scale, wall_depth)
        if used < max(MIN_BEAMS, MIN_BEAM_FRACTION * z.size) or not math.isfinite(s):
            return False
        lo, hi = self.limits
        self.scale = min(max(self.scale + self.alpha * (min(max(s, lo), hi) - self.scale), lo), hi)
        self.updates += 1
        return True
