"""Step 3 of the package doc: batch least squares over every pose and the odometry's speed scale,
the time offset from its profile, the bag's own noise scales and the χ² gate on the matches."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from localization.core.geometry import compose, relative
from localization.eval.reference.constants import (
    CHI2_3_999,
    NP,
    OFFSET_FIT_S,
    OFFSET_PRIOR,
    OFFSET_RANGE,
    OFFSET_STEP_S,
    SCALE_BOUNDS,
    SCALE_PRIOR,
)
from localization.eval.reference.geometry import relative_difference
from localization.eval.reference.marginals import _marginal_covariances
from localization.eval.reference.odometry import OdometryNoise, dead_reckon, odometry_chain
from localization.eval.reference.tracker import Matches

PROFILE_BLOCK = 60_000  # offsets × scans dead-reckoned in one pass of the offset profile (bounds its memory)


@dataclass
class Smoothed:
    poses: np.ndarray  # (K, 3)
    covariance: np.ndarray  # (K, 3, 3)
    params: np.ndarray  # (2,) a, δ
    param_sigma: np.ndarray  # (2,)
    accepted: np.ndarray  # (K,) bool: matches kept after the χ² gate
    chi2: np.ndarray  # (K,) of every usable match against the smoothed track
    scales: dict  # noise scales s_m, s_x, s_y, s_θ
    nfev: int


class _Graph:
    """The least-squares problem of step 3 (package doc): residuals and their sparse Jacobian."""

    def __init__(self, t, Z, info, use, odometry, noise, scales, offset: float = 0.0):
        self.t = np.asarray(t, dtype=float)
        self.offset = float(offset)  # δ, held
        self.K = len(self.t)
        self.Z = Z
        self.idx = np.flatnonzero(use)
        Lam = info[self.idx] / scales["match"] ** 2 + np.diag([1e-8, 1e-8, 1e-8])
        self.Lt = np.transpose(np.linalg.cholesky(Lam), (0, 2, 1))  # r = Lᵀ e, ‖r‖² = eᵀΛe
        self.odo_t, self.odo_tw = odometry
        self.noise, self.scales = noise, scales
        self.sig = None
        K, nm = self.K, len(self.idx)
        # the Jacobian's pattern: odometry factor j (rows 3j..3j+2) on poses j, j+1 and the NP unknowns,
        # match i on its pose, the priors on the unknowns
        j = np.arange(K - 1)
        cols_odo = np.concatenate([3 * j[:, None] + np.arange(6), np.broadcast_to(3 * K + np.arange(NP), (K - 1, NP))],
                                  axis=1)  # (K−1, 6 + NP)
        rows = [np.repeat(3 * j[:, None] + np.arange(3), 6 + NP, axis=1).reshape(-1),
                3 * (K - 1) + np.repeat(3 * np.arange(nm)[:, None] + np.arange(3), 3, axis=1).reshape(-1),
                3 * (K - 1) + 3 * nm + np.arange(NP)]
        cols = [np.repeat(cols_odo[:, None, :], 3, axis=1).reshape(-1),
                np.tile(3 * self.idx[:, None] + np.arange(3), (1, 3)).reshape(-1),
                3 * K + np.arange(NP)]
        self.rows, self.cols = np.concatenate(rows), np.concatenate(cols)
        self.shape = (3 * (K - 1) + 3 * nm + NP, 3 * K + NP)

    def predicted(self, p) -> np.ndarray:
        B = dead_reckon(self.odo_t, self.odo_tw, self.t - self.offset, p[0])
        return relative(B[:-1], B[1:])

    def set_sigmas(self, p):
        pred = self.predicted(p)
        s = self.noise.sigmas(pred, np.diff(self.t))
        s *= np.array([self.scales["odo_x"], self.scales["odo_y"], self.scales["odo_theta"]])
        self.sig = s

    def split(self, z):
        return z[:3 * self.K].reshape(self.K, 3), z[3 * self.K:]

    def parts(self, z):
        X, p = self.split(z)
        r_odo = relative_difference(relative(X[:-1], X[1:]), self.predicted(p)) / self.sig
        e = relative_difference(X[self.idx], self.Z[self.idx])
        r_m = np.einsum("kij,kj->ki", self.Lt, e)
        r_p = (p - 1.0) / SCALE_PRIOR
        return r_odo, r_m, r_p

    def residuals(self, z):
        r_odo, r_m, r_p = self.parts(z)
        return np.concatenate([r_odo.ravel(), r_m.ravel(), r_p])

    def offset_profile(self, X, offsets) -> tuple[np.ndarray, np.ndarray]:
        """Cost of the odometry factors over time offsets δ with the poses X held, a in closed form
        for each (the translation is linear in a): (cost (G,), a (G,)). The loss is Cauchy's,
        ½ c² log(1 + r²/c²) with c = 3: bounded, so a skid or a wheel spin (the odometry far off for
        a while) cannot pull the lowest point to an offset that hides it.

        The dead-reckoned motion between two scans is piecewise smooth in δ, with a kink wherever a
        scan's time crosses an odometry stamp; with noisy twists the kinks make local minima, so δ
        is started from the best of this profile rather than from 0.

        Blocks of offsets × every scan in one vectorised pass each (``offset_profile_loop``: one
        offset at a time, the reference it equals)."""
        rel = relative(X[:-1], X[1:])
        chain = odometry_chain(self.odo_t, self.odo_tw)
        offsets = np.asarray(offsets, dtype=float)
        cost, scale = np.zeros(len(offsets)), np.ones(len(offsets))
        rows = max(1, PROFILE_BLOCK // max(self.K, 1))
        for i in range(0, len(offsets), rows):
            cost[i:i + rows], scale[i:i + rows] = self._profile_block(rel, chain, offsets[i:i + rows])
        return cost, scale

    def _profile_block(self, rel, chain, offsets) -> tuple[list, list]:
        """``offset_profile`` for a few offsets (G,): every scan's dead-reckoned motion at each at once."""
        G, K = len(offsets), self.K
        w = 1.0 / self.sig ** 2
        query = (self.t[None, :] - offsets[:, None]).ravel()
        B = dead_reckon(self.odo_t, self.odo_tw, query, chain=chain).reshape(G, K, 3)
        pred = relative(B[:, :-1], B[:, 1:])
        den = np.sum(w[:, :2] * pred[..., :2] ** 2, axis=(1, 2))
        num = np.sum(w[:, :2] * pred[..., :2] * rel[:, :2], axis=(1, 2))
        scale = [float(np.clip(n / float(d), *SCALE_BOUNDS)) if float(d) > 0 else 1.0 for n, d in zip(num, den)]
        pred[..., :2] *= np.array(scale)[:, None, None]
        r2 = (relative_difference(rel, pred) / self.sig) ** 2 / 9.0
        loss = np.sum(np.log1p(r2), axis=(1, 2))
        cost = [4.5 * loss[g] + 0.5 * ((scale[g] - 1.0) / SCALE_PRIOR) ** 2 + 0.5 * (offsets[g] / OFFSET_PRIOR) ** 2
                for g in range(G)]
        return cost, scale

    def offset_profile_loop(self, X, offsets) -> tuple[np.ndarray, np.ndarray]:
        """``offset_profile`` one offset at a time (its reference, tests)."""
        rel = relative(X[:-1], X[1:])
        chain = odometry_chain(self.odo_t, self.odo_tw)
        w = 1.0 / self.sig ** 2
        cost, scale = np.zeros(len(offsets)), np.ones(len(offsets))
        for i, d in enumerate(offsets):
            B = dead_reckon(self.odo_t, self.odo_tw, self.t - d, chain=chain)
            pred = relative(B[:-1], B[1:])
            den = float(np.sum(w[:, :2] * pred[:, :2] ** 2))
            a = float(np.clip(np.sum(w[:, :2] * pred[:, :2] * rel[:, :2]) / den, *SCALE_BOUNDS)) if den > 0 else 1.0
            pred[:, :2] *= a
            r2 = (relative_difference(rel, pred) / self.sig) ** 2 / 9.0
            cost[i] = 4.5 * np.sum(np.log1p(r2)) + 0.5 * ((a - 1.0) / SCALE_PRIOR) ** 2 \
                + 0.5 * (d / OFFSET_PRIOR) ** 2
            scale[i] = a
        return cost, scale

    def jacobian(self, z):
        """The residuals' Jacobian (sparse, CSR): poses in closed form, the odometry unknowns by
        forward differences of the dead-reckoned odometry."""
        from scipy.sparse import csr_matrix
        X, p = self.split(z)
        K = self.K
        ca, sa = np.cos(X[:-1, 2]), np.sin(X[:-1, 2])
        dx, dy = X[1:, 0] - X[:-1, 0], X[1:, 1] - X[:-1, 1]
        D = np.zeros((K - 1, 3, 6 + NP))
        # rel_xy = R(−θa) (pb − pa): ∂/∂pa = −R(−θa), ∂/∂θa = R'(−θa)(pb − pa), ∂/∂pb = R(−θa)
        D[:, 0, 0], D[:, 0, 1], D[:, 0, 2] = -ca, -sa, -sa * dx + ca * dy
        D[:, 1, 0], D[:, 1, 1], D[:, 1, 2] = sa, -ca, -ca * dx - sa * dy
        D[:, 0, 3], D[:, 0, 4] = ca, sa
        D[:, 1, 3], D[:, 1, 4] = -sa, ca
        D[:, 2, 2], D[:, 2, 5] = -1.0, 1.0
        pred = self.predicted(p)
        for i, h in enumerate((1e-6,)):
            q = p.copy()
            q[i] += h
            D[:, :, 6 + i] = -relative_difference(self.predicted(q), pred) / h
        D /= self.sig[:, :, None]
        data = np.concatenate([D.reshape(-1), self.Lt.reshape(-1),
                               np.full(NP, 1.0 / SCALE_PRIOR)])
        return csr_matrix((data, (self.rows, self.cols)), shape=self.shape)


def _redundancy(graph: _Graph, jac, cov, cov_next) -> tuple[np.ndarray, np.ndarray]:
    """Redundancy numbers (Förstner): per odometry row (K−1, 3) and per match (nm,), r = dof − tr(J Σ Jᵀ),
    J the factor's whitened rows, Σ the covariance of the poses it touches (the odometry unknowns'
    share neglected)."""
    from scipy.sparse import csr_matrix
    J = csr_matrix(jac)
    K = graph.K
    dense = J[:3 * (K - 1), :3 * K]
    rows = np.zeros((K - 1, 3, 6))
    coo = dense.tocoo()
    j = coo.row // 3
    c = coo.col - 3 * j
    ok = (c >= 0) & (c < 6)
    rows[j[ok], coo.row[ok] % 3, c[ok]] = coo.data[ok]
    S = np.zeros((K - 1, 6, 6))
    S[:, :3, :3], S[:, 3:, 3:] = cov[:-1], cov[1:]
    S[:, :3, 3:] = cov_next
    S[:, 3:, :3] = np.transpose(cov_next, (0, 2, 1))
    r_odo = 1.0 - np.einsum("kai,kij,kaj->ka", rows, S, rows)
    m = len(graph.idx)
    Jm = np.zeros((m, 3, 3))
    mc = J[3 * (K - 1):3 * (K - 1) + 3 * m].tocoo()
    i = mc.row // 3
    Jm[i, mc.row % 3, mc.col - 3 * graph.idx[i]] = mc.data
    r_m = 3.0 - np.einsum("kai,kij,kaj->k", Jm, cov[graph.idx], Jm)
    return np.clip(r_odo, 0.0, 1.0), np.clip(r_m, 0.0, 3.0)


def _variance_factor(chi2, redundancy, gate) -> float:
    """Σχ² / Σr (variance component estimation) over the factors within ``gate`` × the factor itself
    (iterated: the gate follows the estimate, so a heavy tail neither sets nor escapes it); 1
    without redundancy."""
    f = 1.0
    for _ in range(20):
        keep = chi2 <= gate * f
        den = float(np.sum(redundancy[keep]))
        if den <= 1.0:
            return f
        new = float(np.sum(chi2[keep]) / den)
        if abs(new - f) <= 1e-3 * f:
            return new
        f = new
    return f


def smooth_track(t, matches: Matches, odometry, noise: OdometryNoise | None = None, log=None) -> Smoothed:
    """Steps 3 and 4 of the package doc."""
    from scipy.optimize import least_squares
    say = log or (lambda *_: None)
    noise = noise or OdometryNoise()
    t = np.asarray(t, dtype=float)
    K = len(t)
    use = matches.usable.copy()
    scales = {"match": 1.0, "odo_x": 1.0, "odo_y": 1.0, "odo_theta": 1.0}
    x0 = np.where(np.isfinite(matches.filtered), matches.filtered, 0.0)
    # scans before the first estimate: carried back by the odometry
    first = int(np.argmax(np.all(np.isfinite(matches.filtered), axis=1)))
    if first > 0:
        B = dead_reckon(*odometry, t)
        x0[:first] = compose(matches.filtered[first], relative(B[first], B[:first]))
    z = np.concatenate([x0.ravel(), [1.0]])
    nfev = 0
    offset, offset_sigma = 0.0, OFFSET_PRIOR
    for stage in range(3):  # solve; then twice: the bag's own noise scales, the χ² gate, solve again
        graph = _Graph(t, matches.poses, matches.information, use, odometry, noise, scales, offset)
        graph.set_sigmas(z[3 * K:])
        offset, offset_sigma, z[3 * K] = fit_offset(graph, z[:3 * K].reshape(K, 3))
        graph = _Graph(t, matches.poses, matches.information, use, odometry, noise, scales, offset)
        graph.set_sigmas(z[3 * K:])
        sol = least_squares(graph.residuals, z, jac=graph.jacobian, loss="soft_l1", f_scale=3.0, x_scale="jac",
                            method="trf", max_nfev=200, xtol=1e-10, ftol=1e-10,
                            tr_options={"atol": 1e-10, "btol": 1e-10})
        if not np.all(np.isfinite(sol.x)) or not SCALE_BOUNDS[0] <= sol.x[3 * K] <= SCALE_BOUNDS[1]:
            raise ValueError(f"the smoothing diverged (odometry speed scale {sol.x[3 * K]:.3g}): odometry unusable")
        z, nfev = sol.x, nfev + sol.nfev
        cov, cov_next, pcov = _marginal_covariances(sol.jac, K)
        if stage == 2:
            break
        r_odo, r_m, _ = graph.parts(z)
        red_odo, red_m = _redundancy(graph, sol.jac, cov, cov_next)
        chi_m = np.sum(r_m ** 2, axis=1)
        f_m = _variance_factor(chi_m, red_m, CHI2_3_999)
        for i, key in enumerate(("odo_x", "odo_y", "odo_theta")):
            scales[key] *= math.sqrt(np.clip(_variance_factor(r_odo[:, i] ** 2, red_odo[:, i], 9.0), 0.01, 100.0))
        scales["match"] *= math.sqrt(np.clip(f_m, 0.01, 100.0))
        scales["match"] = max(scales["match"], 1.0)  # never more certain than the beams say
        bad = graph.idx[chi_m / max(f_m, 1.0) > CHI2_3_999]
        use[bad] = False
        say(f"smoothing: {sol.nfev} evaluations; noise scales: matches {scales['match']:.2f}, odometry x "
            f"{scales['odo_x']:.2f}, y {scales['odo_y']:.2f}, heading {scales['odo_theta']:.2f}; {bad.size} matches "
            f"rejected; odometry time offset {offset * 1e3:+.1f} ms")
    X, p = graph.split(z)
    chi2 = np.full(K, np.nan)
    cand = np.flatnonzero(matches.usable)
    if cand.size:
        e = relative_difference(X[cand], matches.poses[cand])
        Lam = matches.information[cand] / scales["match"] ** 2
        chi2[cand] = np.einsum("ki,kij,kj->k", e, Lam, e)
    psig = np.array([math.sqrt(max(float(pcov[0, 0]), 0.0)), offset_sigma])
    return Smoothed(poses=X.copy(), covariance=cov, params=np.array([p[0], offset]), param_sigma=psig,
                    accepted=use & (np.nan_to_num(chi2, nan=np.inf) <= CHI2_3_999), chi2=chi2, scales=dict(scales),
                    nfev=int(nfev))


def fit_offset(graph: _Graph, X) -> tuple[float, float, float]:
    """δ (s), its σ and the speed scale a at δ from the profile of the odometry factors (package doc,
    step 3): the lowest point of the profile over ± OFFSET_RANGE, then a parabola fitted within
    ± OFFSET_FIT_S of it (its vertex, σ = (½ / curvature)^½; the lowest point itself and the fit's
    half-width when the profile is not convex there)."""
    grid = np.arange(-OFFSET_RANGE, OFFSET_RANGE + 1e-9, OFFSET_STEP_S)
    cost, scale = graph.offset_profile(X, grid)
    i = int(np.argmin(cost))
    near = np.abs(grid - grid[i]) <= OFFSET_FIT_S + 1e-9
    c2, c1, _ = np.polyfit(grid[near] - grid[i], cost[near], 2)
    if c2 <= 0:
        return float(grid[i]), OFFSET_FIT_S, float(scale[i])
    vertex = float(np.clip(-c1 / (2 * c2), -OFFSET_FIT_S, OFFSET_FIT_S)) + float(grid[i])
    return vertex, math.sqrt(0.5 / c2), float(np.interp(vertex, grid, scale))
