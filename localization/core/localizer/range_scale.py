"""Online estimate of the lidar-to-map range scale (``range_scale_estimation``).

The beam model scores a return z (lidar metres) as s·z − o map metres against the range d ray cast in
the map (s = ``lidar_scale_to_map_scale``, o = ``map_wall_depth``). When the building is a little
larger or smaller than its map (or the lidar's range calibration is off), every return is a fixed
factor too long or too short, and the best fit of the beam model moves along the corridor: walls ahead
read farther, so the estimate falls behind the car. This estimator follows that factor while the filter
tracks. Each sensor update fits the scale jointly with a small correction Δ = (Δx, Δy, Δθ) of the
filter's estimate x̂, so that an error of x̂ does not move the scale:

    d_b(x)  = the range of beam b ray cast from pose x (map metres; from its own, deskewed, laser pose)
    J_b     = ∂d_b/∂x at x̂: central differences over ± JACOBIAN_STEP_M in x, y and ± JACOBIAN_STEP_RAD in θ;
              a beam whose one-sided differences disagree by more than CURVATURE_M (a corner, an edge, an
              occlusion that changes within the steps) is not used
    beam b is used when   r_min < z_b < r_max − RANGE_MARGIN_M,   d_b < reach − RANGE_MARGIN_M
                          and  |ŝ·z_b − J_b Δ − o − d_b| ≤ GATE_M + GATE_FRACTION · d_b
    (ŝ, Δ)  = argmin Σ_b (ŝ·z_b − J_b Δ − (d_b + o))² + Δᵀ P⁻¹ Δ · BEAM_STD_M²
              (linear least squares; P = diag(PRIOR_STD_M², PRIOR_STD_M², PRIOR_STD_RAD²) only keeps Δ
              defined along a direction no beam constrains; the gate starts at (s, 0) and is re-centred
              on the first fit, once)
    x̂ ← x̂ + Δ and the fit is repeated GAUSS_NEWTON_STEPS times (ranges are not linear in θ far along
              a corridor's side walls); the last ŝ counts
    s       ← s + α (clip(ŝ, s₀ (1 − β), s₀ (1 + β)) − s)

s₀ is the configured ``lidar_scale_to_map_scale`` (the start value and the centre of the bounds),
α = ``range_scale_alpha`` (per sensor update: a time constant of 1/α updates), β = ``range_scale_bound``.
reach is the farthest range the model casts (its table's, 10 m by default). A scan counts only when at
least ``MIN_BEAM_FRACTION`` of its beams (and ``MIN_BEAMS``) pass the gate and the cloud has converged
(largest position standard deviation ≤ ``MAX_SPREAD_M``); the Localizer feeds it only while tracking
(not during a global spread, not while holding the pose after "scans disagree with the map", not on a
scan after which the cloud moved to a challenger). Δ is used only inside the fit: the filter's estimate
is not changed.

Why the pose correction: a ratio Σ z·d / Σ z² taken at x̂ as if it were the true pose absorbs x̂'s error.
An estimate lagging 0.1 m in a corridor makes the ranges ahead 0.1 m longer, the ratio follows, the
beam model then favours the lagging pose more, and scale and error feed each other. A scale stretches
every range in proportion to its length while a shift moves each range by the cosine of its incidence,
so the two separate: in a corridor the side walls (which no shift along it changes) and the walls
ahead pin them. Returns shorter than the map says (furniture, people: unmapped obstacles) and longer
ones (glass, open doors) fail the gate unless they lie within a few centimetres of a mapped wall.

``estimate_scale`` is one linear fit (vectorised numpy over the beams), ``range_jacobian`` J from the
casts at ``jacobian_poses``, ``fit_step_numpy`` one Gauss–Newton step from them (the numpy reference of the
compiled ``fit_step_kernel``, one pass over the beams; ``fit_step`` picks it), ``fit_scale`` the steps,
``RangeScaleEstimator`` keeps s.
Measured effects (simulated perturbed worlds, the real bags) are in docs/models.md.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from localization.core.localizer.health import cloud_spread

try:  # a compiled Gauss–Newton step when numba is there (pinned); the numpy reference otherwise
    from numba import njit
except ImportError:  # pragma: no cover
    njit = None

__all__ = ["GATE_FRACTION", "GATE_M", "MAX_SPREAD_M", "MIN_BEAMS", "MIN_BEAM_FRACTION", "RANGE_MARGIN_M",
           "RangeScaleEstimator", "estimate_scale", "fit_scale", "jacobian_poses", "range_jacobian"]

GATE_M = 0.10  # m: a beam is used when s·z − o lies within GATE_M + GATE_FRACTION · d of d ...
GATE_FRACTION = 0.02  # ... (0.3 m at 10 m: room for a 2 % scale error before the first estimate)
RANGE_MARGIN_M = 0.25  # m: beams this close to the lidar's range_max or the model's reach are not used
MIN_BEAMS = 10  # a scan counts with at least this many beams in the gate ...
MIN_BEAM_FRACTION = 0.25  # ... and at least this fraction of the scan's beams
MAX_SPREAD_M = 0.15  # m: ... and the cloud's largest position standard deviation at most this
BEAM_STD_M = 0.05  # m: a gated beam's range noise, against which ...
PRIOR_STD_M = 0.15  # m: ... the pose correction's prior (x, y) keeps the fit defined where a direction is
PRIOR_STD_RAD = 0.05  # rad: ... unconstrained (along a corridor with no wall in reach)
JACOBIAN_STEP_M = 0.10  # m: the estimate shifted by ± this in x and y ...
JACOBIAN_STEP_RAD = 0.01  # rad: ... and in θ for the central differences ∂d/∂(x, y, θ)
CURVATURE_M = 0.05  # m: a beam whose two one-sided differences disagree by more (a corner or edge in reach)
GAUSS_NEWTON_STEPS = 2  # fits, each from the pose the previous one corrected


def estimate_scale(z, d, scale: float, wall_depth: float = 0.0, jacobian=None) -> tuple[float, int, np.ndarray]:
    """(ŝ, beams used, Δ (3,)) of one linear fit: measured ranges ``z`` (lidar metres) against ranges ``d`` ray cast at
    the estimate (map metres), beams already limited to valid ones (finite, inside the lidar's and the
    model's reach). ``jacobian`` (B, 3): ∂d/∂(x, y, θ) of each beam at the estimate; with it the scale is
    fitted jointly with a pose correction Δ (module docstring), so an error of the estimate does not move
    ŝ; without it the estimate is taken as the true pose. The gate is centred on ``scale`` (and Δ = 0)
    first, then on the first fit. (NaN, 0, zeros) when no beam passes."""
    z = np.asarray(z, dtype=float).ravel()
    d = np.asarray(d, dtype=float).ravel() + wall_depth  # the model's o moved to the map side: d + o = s·z
    tolerance = GATE_M + GATE_FRACTION * d
    if jacobian is None:  # the estimate taken as the true pose: ŝ alone
        a, prior = z[:, None], np.zeros(1)
    else:  # (ŝ, Δ); the prior's information on Δ, none on ŝ
        a = np.column_stack([z, -np.asarray(jacobian, dtype=float)])
        prior = np.concatenate([[0.0], (BEAM_STD_M / np.array([PRIOR_STD_M, PRIOR_STD_M, PRIOR_STD_RAD])) ** 2])
    fit = np.zeros(a.shape[1])
    fit[0] = float(scale)
    s, used = math.nan, 0
    for _ in range(2):
        with np.errstate(invalid="ignore"):
            ok = np.abs(a @ fit - d) <= tolerance
        used = int(np.count_nonzero(ok))
        if used == 0:
            return math.nan, 0, np.zeros(3)
        aa = a[ok]
        fit = np.linalg.solve(aa.T @ aa + np.diag(prior), aa.T @ d[ok])
        s = float(fit[0])
    return s, used, (np.zeros(3) if jacobian is None else fit[1:])


def jacobian_poses(pose) -> np.ndarray:
    """(7, 3): the estimate, then shifted by ± ``JACOBIAN_STEP_M`` in x, in y and ± ``JACOBIAN_STEP_RAD``
    in θ: cast the scan's beams from these and pass the (7, B) ranges to ``range_jacobian``."""
    poses = np.empty((7, 3))
    poses[:] = np.asarray(pose, dtype=float).reshape(3)
    poses[1::2] += _SHIFTS  # rows 1, 3, 5: pose + step in x, y, θ
    poses[2::2] -= _SHIFTS  # rows 2, 4, 6: pose − step
    return poses


def range_jacobian(ranges) -> tuple[np.ndarray, np.ndarray]:
    """(J (B, 3), smooth (B,)) from the (7, B) ranges cast from ``jacobian_poses``: central differences
    ∂d/∂(x, y, θ), and whether each beam's range is linear over the steps (its two one-sided differences
    agree within ``CURVATURE_M`` in every direction: no corner, edge or occlusion change in reach)."""
    r = np.asarray(ranges, dtype=float)
    ahead, behind = r[1::2] - r[0], r[0] - r[2::2]  # (3, B) one-sided differences
    step = np.array([JACOBIAN_STEP_M, JACOBIAN_STEP_M, JACOBIAN_STEP_RAD])[:, None]
    with np.errstate(invalid="ignore"):
        smooth = np.all(np.abs(ahead - behind) <= CURVATURE_M, axis=0)
    return ((ahead + behind) / (2.0 * step)).T, smooth


def fit_step_numpy(z, ranges, valid, scale: float, wall_depth: float = 0.0) -> tuple[float, int, np.ndarray]:
    """(ŝ, beams used, Δ (3,)) of one Gauss–Newton step from the (7, B) ranges cast at ``jacobian_poses``:
    J and the smooth beams (``range_jacobian``), the valid smooth beams fitted (``estimate_scale``)."""
    jacobian, smooth = range_jacobian(ranges)
    ok = valid & smooth & np.isfinite(ranges[0])
    if not ok.any():
        return math.nan, 0, np.zeros(3)
    return estimate_scale(z[ok], ranges[0][ok], scale, wall_depth, jacobian[ok])


_STEPS = np.array([JACOBIAN_STEP_M, JACOBIAN_STEP_M, JACOBIAN_STEP_RAD])
_SHIFTS = np.diag(_STEPS)  # row k: the step in coordinate k
_PRIOR = np.concatenate([[0.0], (BEAM_STD_M / np.array([PRIOR_STD_M, PRIOR_STD_M, PRIOR_STD_RAD])) ** 2])

if njit is not None:
    @njit(cache=True, nogil=True)
    def fit_step_kernel(z, ranges, valid, scale, wall_depth, steps, prior, fit):  # pragma: no cover - compiled
        """``fit_step_numpy`` in one pass over the beams: ``fit`` (4,) receives (ŝ, Δx, Δy, Δθ); returns the
        beams used (0: none, ``fit`` NaN). The normal equations are summed beam by beam and solved by Gaussian
        elimination with partial pivoting (what ``np.linalg.solve`` does, summed in another order)."""
        n = z.size
        jac = np.empty((n, 3))
        ok = np.zeros(n, dtype=np.bool_)
        for b in range(n):
            r0 = ranges[0, b]
            smooth = True
            for k in range(3):
                ahead = ranges[1 + 2 * k, b] - r0
                behind = r0 - ranges[2 + 2 * k, b]
                if not abs(ahead - behind) <= CURVATURE_M:
                    smooth = False
                jac[b, k] = (ahead + behind) / (2.0 * steps[k])
            ok[b] = valid[b] and smooth and math.isfinite(r0)
        cur = np.array([scale, 0.0, 0.0, 0.0])
        m = np.empty((4, 4))
        rhs = np.empty(4)
        a = np.empty(4)
        used = 0
        for _ in range(2):  # the gate centred on (scale, 0), then on the first fit
            m[:, :] = 0.0
            rhs[:] = 0.0
            used = 0
            for b in range(n):
                if not ok[b]:
                    continue
                d = ranges[0, b] + wall_depth
                a[0] = z[b]
                a[1] = -jac[b, 0]
                a[2] = -jac[b, 1]
                a[3] = -jac[b, 2]
                pred = a[0] * cur[0] + a[1] * cur[1] + a[2] * cur[2] + a[3] * cur[3]
                if not abs(pred - d) <= GATE_M + GATE_FRACTION * d:
                    continue
                used += 1
                for i in range(4):
                    rhs[i] += a[i] * d
                    for k in range(4):
                        m[i, k] += a[i] * a[k]
            if used == 0:
                fit[:] = np.nan
                return 0
            for i in range(4):
                m[i, i] += prior[i]
            for col in range(4):  # Gaussian elimination with partial pivoting
                piv = col
                for r in range(col + 1, 4):
                    if abs(m[r, col]) > abs(m[piv, col]):
                        piv = r
                if piv != col:
                    for k in range(4):
                        m[col, k], m[piv, k] = m[piv, k], m[col, k]
                    rhs[col], rhs[piv] = rhs[piv], rhs[col]
                for r in range(col + 1, 4):
                    f = m[r, col] / m[col, col]
                    for k in range(col, 4):
                        m[r, k] -= f * m[col, k]
                    rhs[r] -= f * rhs[col]
            for i in range(3, -1, -1):
                acc = rhs[i]
                for k in range(i + 1, 4):
                    acc -= m[i, k] * cur[k]
                cur[i] = acc / m[i, i]
        fit[:] = cur
        return used
else:  # pragma: no cover
    fit_step_kernel = None


def fit_step(z, ranges, valid, scale: float, wall_depth: float = 0.0) -> tuple[float, int, np.ndarray]:
    """``fit_step_numpy``, compiled (``fit_step_kernel``) when numba is there."""
    if fit_step_kernel is None:
        return fit_step_numpy(z, ranges, valid, scale, wall_depth)
    fit = np.empty(4)
    used = fit_step_kernel(np.ascontiguousarray(z, dtype=float), np.ascontiguousarray(ranges, dtype=float),
                           np.ascontiguousarray(valid, dtype=np.bool_), float(scale), float(wall_depth), _STEPS,
                           _PRIOR, fit)
    return (float(fit[0]), int(used), fit[1:].copy()) if used else (math.nan, 0, np.zeros(3))


def fit_scale(z, cast, pose, valid, scale: float, wall_depth: float = 0.0,
              steps: int = GAUSS_NEWTON_STEPS, ranges=None) -> tuple[float, int]:
    """(ŝ, beams used) of one scan fitted jointly with a pose correction (module docstring): measured
    ranges ``z`` (lidar metres), ``cast(poses (k, 3)) -> (k, B)`` ray casts the scan's beams (map
    metres), ``pose`` the filter's estimate, ``valid`` (B,) the beams worth fitting, ``steps`` the
    Gauss-Newton steps, ``ranges`` the (7, B) casts from ``jacobian_poses(pose)`` when already cast.
    (NaN, 0) when no beam passes."""
    z = np.asarray(z, dtype=float).ravel()
    pose = np.asarray(pose, dtype=float).reshape(3)
    s, used = math.nan, 0
    for _ in range(steps):
        ranges = np.asarray(cast(jacobian_poses(pose)) if ranges is None else ranges, dtype=float)
        s, used, correction = fit_step(z, ranges, valid, scale, wall_depth)
        if not math.isfinite(s):
            return math.nan, 0
        pose, ranges = pose + correction, None
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

    def update(self, z, cast, pose, range_min: float, range_max: float, reach: float, covariance=None,
               wall_depth: float = 0.0) -> bool:
        """One scan: measured ranges ``z`` (lidar metres, NaN/inf for no return), ``cast(poses (k, 3)) ->
        (k, B)`` the same beams ray cast from poses (map metres), ``pose`` the filter's estimate, the scan's
        ``range_min``/``range_max``, the model's ``reach`` (map metres), the cloud's ``covariance`` (3, 3)
        (None: not checked). True when s moved."""
        if covariance is not None and not cloud_spread(covariance) <= MAX_SPREAD_M:
            return False
        z = np.asarray(z, dtype=float).ravel()
        ranges = np.asarray(cast(jacobian_poses(pose)), dtype=float)  # the first fit's casts; d: from the estimate
        d = ranges[0]
        with np.errstate(invalid="ignore"):
            valid = (np.isfinite(z) & np.isfinite(d) & (z > range_min) & (z < range_max - RANGE_MARGIN_M)
                     & (d > 0.0) & (d < reach - RANGE_MARGIN_M))
        if np.count_nonzero(valid) < MIN_BEAMS:
            return False
        s, used = fit_scale(z, cast, pose, valid, self.scale, wall_depth, ranges=ranges)
        if used < max(MIN_BEAMS, MIN_BEAM_FRACTION * z.size) or not math.isfinite(s):
            return False
        lo, hi = self.limits
        self.scale = min(max(self.scale + self.alpha * (min(max(s, lo), hi) - self.scale), lo), hi)
        self.updates += 1
        return True
