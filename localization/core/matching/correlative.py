"""Correlative scan-to-map matching (Olson, "Real-time correlative scan matching", ICRA 2009),
then a sub-cell Gauss–Newton finish.

Given a full scan (ranges r_i at angles a_i in the laser frame, invalid = inf), the laser mount
m = (m_x, m_y, m_ψ) in base_link and a seed base pose, find the base pose x = (x, y, θ) in a window
around the seed that best explains the scan in the map. Beam i's endpoint in base_link and in the
map::

    q_i = (m_x, m_y) + s r_i (cos(m_ψ + a_i), sin(m_ψ + a_i))          (s: range scale, default 1)
    p_i(x) = (x, y) + R(θ) q_i

Score of a pose: the mean likelihood of its endpoints (``grids.likelihood_grid``)::

    S(x) = (1/n) Σ_i L(p_i(x)),   L = exp(−d²/2σ²),  d = distance to the nearest wall face

1. Search (in the grid frame, whole cells): rotations θ_j = θ_seed + j Δθ (|j| ≤ J), and for each
   the endpoints rounded to cells once; translations are then whole-cell shifts (du, dv), |du|, |dv| ≤ W.
   The rotation step is sized so that the farthest endpoint moves at most one cell per step::

       Δθ = min(Δθ_max, res / max_i |q_i|)      (rad; res in m, |q_i| in m; ``angle_step`` fixes it)

   Coarse level: blocks of k × k shifts scored on the max-pooled grid (an upper bound of every
   fine score in the block, the grid padded on both sides so that it bounds blocks straddling
   either edge of the map); blocks sorted by bound are expanded at full resolution until no
   remaining bound beats the best fine score (branch and bound: the result equals the exhaustive
   search over the whole window). Every valid beam is used at both levels (no decimation unless
   ``max_beams`` says so), so the bound is exact.
2. Covariance from the score distribution around the peak (Olson §IV-C): over the fine shifts
   |δu|, |δv| ≤ W_c and rotations |δj| ≤ J_c around the peak, weights w = exp((S − S_max)/T)::

       μ = Σ w x / Σ w,   Σ = Σ w (x − μ)(x − μ)ᵀ / Σ w   (+ the cell's own quantisation, res²/12)

   The match is *ambiguous* when the standard deviation along its worst direction in x, y
   exceeds ``ambiguous_std`` (a featureless corridor: the score is flat along it), or when the peak
   lies on the edge of the search window (the optimum may be outside).
3. Sub-cell finish: Gauss–Newton on the bilinearly interpolated signed distance d(p) (cells),
   Cauchy-weighted (w_i = 1/(1 + (d_i/c)²), beams with |d_i| > 4c dropped)::

       min_x Σ_i w_i d(p_i(x))²,    J_i = ∇d(p_i) · [I | R'(θ) q_i]

   accepted when it stays within one search step of the discrete peak.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from localization.core.geometry import wrap_angle
from localization.core.matching import kernels as K
from localization.core.matching.grids import likelihood_grid, pool_pad, pooled_likelihood_grid, signed_distance
from localization.core.occupancy_map import OccupancyMap


@dataclass(frozen=True)
class MatcherConfig:
    """Search window, resolution and scoring of the correlative matcher."""

    window_xy: float = 0.4  # m: search ± this around the seed in x and y
    window_theta: float = 0.2  # rad: search ± this around the seed heading
    angle_step: float | None = None  # rad between candidate rotations; None: sized per scan (module doc, step 1)
    max_angle_step: float = 0.02  # rad: the coarsest sized step (every endpoint within 50 cells of the base)
    coarse_step: int = 4  # cells per side of a coarse block
    sigma: float = 0.075  # m: width of the endpoint likelihood
    max_range: float = 30.0  # m: beams beyond are not used
    max_beams: int | None = None  # None: every valid beam; else evenly decimated to this many
    cov_window: int = 6  # cells: ± fine shifts scored for the covariance
    cov_angles: int = 4  # ± rotation steps scored for the covariance
    temperature: float = 0.01  # score units: weight exp((S - S_max)/T) of a pose in the covariance
    ambiguous_std: float = 0.08  # m: std along the worst xy direction above which a match is ambiguous
    refine: bool = True  # Gauss–Newton sub-cell finish
    refine_iterations: int = 10
    huber_cells: float = 1.0  # Cauchy scale c (cells) of the refinement


@dataclass
class MatchResult:
    """The best base pose for one scan, with its quality."""

    pose: np.ndarray  # (3,) base_link pose in the map (x, y, θ)
    laser_pose: np.ndarray  # (3,) the laser's pose in the map (pose ⊕ mount)
    score: float  # mean endpoint likelihood S ∈ [0, 1] at the discrete peak
    covariance: np.ndarray  # (3, 3) of (x, y, θ), m² / rad²
    ambiguous: bool  # the score does not pin the pose down (see module doc)
    at_window_edge: bool  # the discrete peak is on the edge of the search window
    num_beams: int  # valid beams used
    refined: bool  # the Gauss–Newton finish was applied
    inlier_fraction: float  # beams ending within 2 σ of a wall face at the final pose
    angle_step: float = math.nan  # rad between the candidate rotations searched

    @property
    def std_xy_max(self) -> float:
        """Standard deviation (m) along the worst-determined horizontal direction."""
        return float(math.sqrt(max(np.linalg.eigvalsh(self.covariance[:2, :2]).max(), 0.0)))


def endpoints_base(ranges, angles, mount, range_scale: float = 1.0, max_range: float = np.inf, beam_dt=None,
                   twist=None):
    """Valid beams' endpoints (n, 2) in base_link, and their ranges (n,), (finite, 0 < r ≤ max_range).

    Deskew (``beam_dt``: each beam's time after the reference time, ``twist`` = (vx, vy, ωz) of the
    base): a beam measured τ later, when the base had moved by Δ(τ) = integrate_twist(vx, vy, ωz, τ),
    ends at Δ(τ) ⊕ q in the base frame of the reference time."""
    r = np.asarray(ranges, dtype=float).ravel() * range_scale
    a = np.asarray(angles, dtype=float).ravel()
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(r) & (r > 0) & (r <= max_range)
    r, a = r[ok], a[ok]
    mx, my, myaw = (float(v) for v in mount)
    q = np.empty((r.size, 2))
    q[:, 0] = mx + r * np.cos(myaw + a)
    q[:, 1] = my + r * np.sin(myaw + a)
    if beam_dt is not None and twist is not None:
        tau = np.asarray(beam_dt, dtype=float).ravel()[ok]
        vx, vy, wz = (float(v) for v in twist)
        dth = wz * tau
        small = np.abs(dth) < 1e-9
        safe = np.where(small, 1.0, wz)
        sa = np.where(small, tau, np.sin(dth) / safe)
        ca = np.where(small, 0.5 * dth * tau, (1.0 - np.cos(dth)) / safe)
        dx, dy = vx * sa - vy * ca, vx * ca + vy * sa
        c, s = np.cos(dth), np.sin(dth)
        q = np.stack([dx + c * q[:, 0] - s * q[:, 1], dy + s * q[:, 0] + c * q[:, 1]], axis=1)
    return q, r


class CorrelativeMatcher:
    """Scan-to-map matcher for one map (its grids are built once and cached on the map)."""

    def __init__(self, occupancy_map: OccupancyMap, config: MatcherConfig | None = None):
        self.map = occupancy_map
        self.config = config or MatcherConfig()
        c = self.config
        self.res = occupancy_map.resolution
        self.L = likelihood_grid(occupancy_map, c.sigma)
        self.P = pooled_likelihood_grid(occupancy_map, c.sigma, c.coarse_step)  # padded by pool_pad on the low side
        self.pad = pool_pad(c.coarse_step)
        self.sdf = signed_distance(occupancy_map)
        self.yaw0 = occupancy_map.origin[2]

    # ------------------------------------------------------------------ frames
    def _to_grid(self, pose) -> np.ndarray:
        return self.map.world_to_grid_pose(np.asarray(pose, dtype=float))

    def _to_world(self, g) -> np.ndarray:
        xy = self.map.grid_to_world(np.asarray(g[:2], dtype=float) - 0.5)
        return np.array([xy[0], xy[1], float(wrap_angle(g[2] + self.yaw0))])

    # ------------------------------------------------------------------ the match
    def match(self, ranges, angles, mount, seed, window_xy: float | None = None,
              window_theta: float | None = None, range_scale: float = 1.0, beam_dt=None,
              twist=None) -> MatchResult | None:
        """Best base pose near ``seed`` for a scan (ranges, angles in the laser frame), the laser
        at ``mount`` (x, y, yaw) in base_link. None when the scan has fewer than 10 valid beams.
        ``beam_dt`` (s per beam) and ``twist`` (vx, vy, ωz) deskew it (``endpoints_base``)."""
        c = self.config
        q, _ = endpoints_base(ranges, angles, mount, range_scale, c.max_range, beam_dt, twist)
        if c.max_beams is not None and len(q) > c.max_beams:
            q = q[np.unique(np.linspace(0, len(q) - 1, c.max_beams).astype(int))]
        n = len(q)
        if n < 10 or not np.all(np.isfinite(np.asarray(seed, dtype=float))):
            return None
        qg = q / self.res  # base-frame endpoints in cells
        wxy = c.window_xy if window_xy is None else window_xy
        wth = c.window_theta if window_theta is None else window_theta
        W = max(1, int(math.ceil(wxy / self.res)))
        step = self.angle_step_for(qg)
        J = max(0, int(math.ceil(wth / step)))
        g0 = self._to_grid(seed)
        phis = g0[2] + np.arange(-J, J + 1) * step
        best, bj, bu, bv, cols, rows = self.search(qg, g0, phis, W)
        at_edge = abs(bu) == W or abs(bv) == W or (J > 0 and abs(bj - J) == J)

        # covariance from the score distribution around the peak
        cov_g = self._covariance(cols, rows, phis, bj, bu, bv, step)
        peak = np.array([g0[0] + bu, g0[1] + bv, phis[bj]])

        refined = False
        final = peak
        if c.refine:
            ref = self._refine(peak, qg, step)
            if ref is not None and np.all(np.abs(ref[:2] - peak[:2]) <= 1.0) and abs(ref[2] - peak[2]) <= step:
                final, refined = ref, True

        pose = self._to_world(final)
        cov = self._cov_to_world(cov_g)
        laser = np.array([pose[0] + math.cos(pose[2]) * mount[0] - math.sin(pose[2]) * mount[1],
                          pose[1] + math.sin(pose[2]) * mount[0] + math.cos(pose[2]) * mount[1],
                          float(wrap_angle(pose[2] + mount[2]))])
        d = self._sdf_at(final, qg)[0] * self.res
        inliers = float(np.mean(np.abs(d) < 2 * c.sigma))
        worst = math.sqrt(max(np.linalg.eigvalsh(cov[:2, :2]).max(), 0.0))
        return MatchResult(pose=pose, laser_pose=laser, score=float(best), covariance=cov,
                           ambiguous=bool(worst > c.ambiguous_std or at_edge), at_window_edge=bool(at_edge),
                           num_beams=n, refined=refined, inlier_fraction=inliers, angle_step=step)

    def angle_step_for(self, qg) -> float:
        """Rotation step (rad) for base-frame endpoints ``qg`` (cells): the farthest moves ≤ 1 cell
        per step, Δθ = min(max_angle_step, 1 / max_i |q_i|) (``angle_step`` when the config fixes it)."""
        c = self.config
        if c.angle_step is not None:
            return float(c.angle_step)
        far = float(np.sqrt((np.asarray(qg, dtype=float) ** 2).sum(axis=1).max())) if len(qg) else 0.0
        return float(c.max_angle_step) if far <= 1.0 / c.max_angle_step else 1.0 / far

    def coarse_bounds(self, cols, rows, cand_j, cand_u, cand_v) -> np.ndarray:
        """Upper bound of the fine score over each block of k × k shifts starting at (cand_u, cand_v)
        (the pooled grid, looked up through its low-side padding)."""
        return K.score_candidates(self.P, cols, rows, cand_j, cand_u + self.pad, cand_v + self.pad)

    def search(self, qg, g0, phis, W: int):
        """Branch and bound over the rotations ``phis`` (grid frame, rad) and the whole-cell shifts
        |du|, |dv| ≤ W of the endpoints ``qg`` (cells, base frame), the base at grid pose ``g0``.
        Returns (best score, j, du, dv, cols, rows): the same best as the exhaustive search."""
        cols, rows = self._cells(g0, phis, qg)
        k = self.config.coarse_step
        starts = np.arange(-W, W + 1, k)
        jj, uu, vv = np.meshgrid(np.arange(len(phis)), starts, starts, indexing="ij")
        cand_j, cand_u, cand_v = (a.ravel().astype(np.int64) for a in (jj, uu, vv))
        bounds = self.coarse_bounds(cols, rows, cand_j, cand_u, cand_v)
        order = np.argsort(-bounds, kind="stable")
        best, bj, bu, bv = K.branch_and_bound(self.L, cols, rows, cand_j[order], cand_u[order], cand_v[order],
                                              bounds[order], k, W)
        return best, bj, bu, bv, cols, rows

    def score(self, ranges, angles, mount, pose, range_scale: float = 1.0) -> float:
        """Mean endpoint likelihood S of a given base pose (the discrete score of the search)."""
        q, _ = endpoints_base(ranges, angles, mount, range_scale, self.config.max_range)
        if len(q) == 0:
            return float("nan")
        g = self._to_grid(pose)
        cols, rows = self._cells(g, np.array([g[2]]), q / self.res)
        return float(K.score_candidates(self.L, cols, rows, np.zeros(1, np.int64), np.zeros(1, np.int64),
                                        np.zeros(1, np.int64))[0])

    def refine_scale(self, ranges, angles, laser_pose, iterations: int = 15):
        """Range multiplier s fitted with the laser pose by Gauss–Newton on the signed distance
        (the finish of step 3 with a fourth unknown, ∂p_i/∂s = R(θ) r_i (cos a_i, sin a_i)), from
        a good ``laser_pose``. None when it does not converge near it."""
        c = self.config
        q, _ = endpoints_base(ranges, angles, (0.0, 0.0, 0.0), 1.0, c.max_range)
        if len(q) < 20:
            return None
        qg = q / self.res
        step_max = self.angle_step_for(qg)
        g = np.append(self._to_grid(laser_pose), 1.0)
        g0 = g.copy()
        ch = c.huber_cells
        for _ in range(iterations):
            d, (gu, gv, gphi) = self._sdf_at(g[:3], qg * g[3], with_gradient=True)
            cphi, sphi = math.cos(g[2]), math.sin(g[2])
            gs = gu * (cphi * qg[:, 0] - sphi * qg[:, 1]) + gv * (sphi * qg[:, 0] + cphi * qg[:, 1])
            step = gauss_newton_step(d, np.stack([gu, gv, gphi, gs], axis=1), ch, 20, 1e-6, 1e-12)
            if step is None:
                return None
            step[:2] = np.clip(step[:2], -0.5, 0.5)
            step[2] = float(np.clip(step[2], -step_max, step_max))
            step[3] = float(np.clip(step[3], -0.01, 0.01))
            g += step
            if np.all(np.abs(step) < [1e-3, 1e-3, 1e-5, 1e-6]):
                break
        if np.any(np.abs(g[:2] - g0[:2]) > 2.0) or abs(g[3] - 1.0) > 0.2:
            return None
        return float(g[3])

    # ------------------------------------------------------------------ pieces
    @staticmethod
    def _cells(g0, phis, qg):
        """Endpoint cells (J, n) int64 for each rotation, the base at grid position g0[:2]."""
        cphi, sphi = np.cos(phis)[:, None], np.sin(phis)[:, None]
        u = g0[0] + cphi * qg[None, :, 0] - sphi * qg[None, :, 1]
        v = g0[1] + sphi * qg[None, :, 0] + cphi * qg[None, :, 1]
        return (np.ascontiguousarray(np.floor(u).astype(np.int64)),
                np.ascontiguousarray(np.floor(v).astype(np.int64)))

    def _covariance(self, cols, rows, phis, bj, bu, bv, angle_step: float) -> np.ndarray:
        """Weighted covariance (grid units: cells, cells, rad) of the scores around the peak."""
        c = self.config
        js = np.arange(max(bj - c.cov_angles, 0), min(bj + c.cov_angles, len(phis) - 1) + 1)
        sh = np.arange(-c.cov_window, c.cov_window + 1)
        jj, uu, vv = np.meshgrid(js, bu + sh, bv + sh, indexing="ij")
        cj, cu, cv = (a.ravel().astype(np.int64) for a in (jj, uu, vv))
        s = K.score_candidates(self.L, cols, rows, cj, cu, cv)
        w = np.exp((s - s.max()) / c.temperature)
        w /= w.sum()
        X = np.stack([cu.astype(float), cv.astype(float), phis[cj]], axis=1)
        mu = w @ X
        D = X - mu
        cov = (D * w[:, None]).T @ D
        cov += np.diag([1 / 12, 1 / 12, angle_step ** 2 / 12])  # the peak's own quantisation
        return cov

    def _cov_to_world(self, cov_g) -> np.ndarray:
        T = np.zeros((3, 3))
        cy, sy = math.cos(self.yaw0), math.sin(self.yaw0)
        T[:2, :2] = np.array([[cy, -sy], [sy, cy]]) * self.res
        T[2, 2] = 1.0
        return T @ cov_g @ T.T

    def _sdf_at(self, g, qg, with_gradient: bool = False):
        """Bilinear signed distance (cells) at the endpoints of grid pose g; optionally its
        gradient w.r.t. the endpoint (du, dv) and the endpoint's derivative w.r.t. φ (``kernels.sdf_at``)."""
        d, gu, gv, gphi = K.sdf_at(self.sdf, g, qg)
        return (d, (gu, gv, gphi)) if with_gradient else (d, None)

    def _refine(self, g, qg, angle_step: float):
        """Gauss–Newton on the Cauchy-weighted signed distance (module doc, step 3); each step's
        rotation is clipped to one search step."""
        c = self.config
        g = np.array(g, dtype=float)
        ch = c.huber_cells
        for _ in range(c.refine_iterations):
            d, (gu, gv, gphi) = self._sdf_at(g, qg, with_gradient=True)
            step = gauss_newton_step(d, np.stack([gu, gv, gphi], axis=1), ch, 10, 1e-3, 1e-9)
            if step is None:
                return None
            step[:2] = np.clip(step[:2], -0.5, 0.5)
            step[2] = float(np.clip(step[2], -angle_step, angle_step))
            g += step
            if abs(step[0]) < 1e-3 and abs(step[1]) < 1e-3 and abs(step[2]) < 1e-5:
                break
        return g


def gauss_newton_step(d, jacobian, cauchy: float, min_inliers: int, damping: float, eps: float):
    """One Cauchy-weighted, damped Gauss–Newton step on the residuals ``d`` (cells):

        w_i = 1 / (1 + (d_i / c)²)  (0 beyond 4c),   step = −(JᵀWJ + λI)⁻¹ JᵀW d,   λ = damping·tr(JᵀWJ)/n + eps

    None when fewer than ``min_inliers`` residuals carry weight or the system is singular."""
    w = 1.0 / (1.0 + (d / cauchy) ** 2)
    w[np.abs(d) > 4 * cauchy] = 0.0
    if np.count_nonzero(w) < min_inliers:
        return None
    n = jacobian.shape[1]
    weighted = jacobian * w[:, None]
    H = weighted.T @ jacobian
    b = weighted.T @ d
    try:
        step = -np.linalg.solve(H + (damping * np.trace(H) / n + eps) * np.eye(n), b)
    except np.linalg.LinAlgError:
        return None
    return step if np.all(np.isfinite(step)) else None
