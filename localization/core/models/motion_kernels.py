"""The motion model's compiled passes (``models.motion``): one piece over the cloud, several pieces in one pass,
each piece's noise covariance Σ(u) and its factor F (F Fᵀ = Σ), and ``MotionModel.evaluate_pieces`` whole (the
factors, the draws, the pass). The numpy references are in ``models.motion``; the tests assert them equal.
"""
from __future__ import annotations

import math

import numpy as np

try:  # numba is pinned; models.motion runs its numpy references without it
    from numba import njit
except ImportError:  # pragma: no cover
    njit = None

if njit is not None:

    @njit(cache=True, nogil=True)
    def move_kernel(particles, odometry, noise, factor, out):  # pragma: no cover - compiled
        """As ``motion.move_reference``: out[i] = particles[i] ⊕ (odometry + factor · noise[i])."""
        noisy = noise.shape[0] == particles.shape[0]
        two_pi = 2.0 * np.pi
        for i in range(particles.shape[0]):
            d0 = odometry[0]
            d1 = odometry[1]
            d2 = odometry[2]
            if noisy:
                n0 = noise[i, 0]
                n1 = noise[i, 1]
                n2 = noise[i, 2]
                d0 = odometry[0] + (factor[0, 0] * n0 + factor[0, 1] * n1 + factor[0, 2] * n2)
                d1 = odometry[1] + (factor[1, 0] * n0 + factor[1, 1] * n1 + factor[1, 2] * n2)
                d2 = odometry[2] + (factor[2, 0] * n0 + factor[2, 1] * n1 + factor[2, 2] * n2)
            th = particles[i, 2]
            c = math.cos(th)
            s = math.sin(th)
            x = particles[i, 0] + c * d0 - s * d1
            y = particles[i, 1] + s * d0 + c * d1
            w = th + d2 + np.pi  # as geometry.wrap_angle; the modulo only outside [0, 2π) (the identity there)
            w = w - np.pi if 0.0 <= w < two_pi else w % two_pi - np.pi
            if w <= -np.pi:
                w += two_pi
            out[i, 0] = x
            out[i, 1] = y
            out[i, 2] = w

    @njit(cache=True, nogil=True)
    def covariance_kernel(vx, vy, w, beta, qa, qc, qt, tau, weights):  # pragma: no cover - compiled
        """As ``motion.covariance_reference``: Σ = Σ_n w_n Φ(τ_n) diag(qa, qc, qt) Φ(τ_n)ᵀ."""
        def arc(t):  # geometry.integrate_twist(vx, vy, w, t)
            dth = w * t
            if abs(dth) < 1e-6:
                a = t * (1.0 - dth * dth / 6.0)
                b = t * 0.5 * dth
            else:
                a = math.sin(dth) / w
                b = (1.0 - math.cos(dth)) / w
            return vx * a - vy * b, vx * b + vy * a
        ex, ey = arc(1.0)
        cov = np.zeros((3, 3))
        phi = np.zeros((3, 3))
        for n in range(tau.size):
            px, py = arc(tau[n])
            ang = w * tau[n] + beta
            c, s = math.cos(ang), math.sin(ang)
            phi[0, 0], phi[0, 1], phi[0, 2] = c, -s, -(ey - py)
            phi[1, 0], phi[1, 1], phi[1, 2] = s, c, ex - px
            phi[2, 0], phi[2, 1], phi[2, 2] = 0.0, 0.0, 1.0
            for i in range(3):
                for k in range(3):
                    cov[i, k] += weights[n] * (phi[i, 0] * qa * phi[k, 0] + phi[i, 1] * qc * phi[k, 1]
                                               + phi[i, 2] * qt * phi[k, 2])
        for i in range(3):
            for k in range(i + 1, 3):
                m = 0.5 * (cov[i, k] + cov[k, i])
                cov[i, k] = m
                cov[k, i] = m
        return cov

    @njit(cache=True, nogil=True)
    def move_pieces_kernel(particles, us, factors, noise, which, out):  # pragma: no cover - compiled
        """``move_kernel`` of piece p = 0 … P − 1 in turn for each particle (noise[which[p], i]; which[p] < 0:
        none), in one pass: the same arithmetic."""
        two_pi = 2.0 * np.pi
        for i in range(particles.shape[0]):
            x = particles[i, 0]
            y = particles[i, 1]
            th = particles[i, 2]
            for p in range(us.shape[0]):
                d0 = us[p, 0]
                d1 = us[p, 1]
                d2 = us[p, 2]
                q = which[p]
                if q >= 0:
                    n0 = noise[q, i, 0]
                    n1 = noise[q, i, 1]
                    n2 = noise[q, i, 2]
                    f = factors[p]
                    d0 = us[p, 0] + (f[0, 0] * n0 + f[0, 1] * n1 + f[0, 2] * n2)
                    d1 = us[p, 1] + (f[1, 0] * n0 + f[1, 1] * n1 + f[1, 2] * n2)
                    d2 = us[p, 2] + (f[2, 0] * n0 + f[2, 1] * n1 + f[2, 2] * n2)
                c = math.cos(th)
                s = math.sin(th)
                x, y = x + c * d0 - s * d1, y + s * d0 + c * d1
                w = th + d2 + np.pi  # as geometry.wrap_angle; the modulo only outside [0, 2π) (the identity there)
                w = w - np.pi if 0.0 <= w < two_pi else w % two_pi - np.pi
                th = w + two_pi if w <= -np.pi else w
            out[i, 0] = x
            out[i, 1] = y
            out[i, 2] = th

    @njit(cache=True, nogil=True)
    def factor_kernel(cov):  # pragma: no cover - compiled
        """As ``motion.noise_factor_numpy``."""
        vals, vecs = np.linalg.eigh(cov)
        out = np.empty((3, 3))
        for j in range(3):
            root = math.sqrt(vals[j]) if vals[j] > 0.0 else 0.0
            for i in range(3):
                out[i, j] = vecs[i, j] * root
        return out

    @njit(cache=True, nogil=True)
    def plan_move_kernel(rng, particles, rows, tau, weights, noise, out):  # pragma: no cover - compiled
        """``MotionModel.evaluate_pieces`` from its rows (``_plan_row``): each piece's Σ(u) (``covariance_kernel``;
        zero when standing), plus the slip's variance, its factor when Σ has a non-zero entry (as ``_plan``);
        the noisy pieces' standard normal draws into noise[0 …] in order (``Generator.standard_normal``'s values
        and state); then ``move_pieces_kernel``."""
        count_pieces = rows.shape[0]
        us = np.empty((count_pieces, 3))
        factors = np.zeros((count_pieces, 3, 3))
        which = np.full(count_pieces, -1, dtype=np.int64)
        noisy = 0
        for p in range(count_pieces):
            us[p, 0] = rows[p, 0]
            us[p, 1] = rows[p, 1]
            us[p, 2] = rows[p, 2]
            if rows[p, 10] == 0.0:  # deterministic
                continue
            if rows[p, 11] != 0.0:
                cov = covariance_kernel(rows[p, 3], rows[p, 4], rows[p, 5], rows[p, 6], rows[p, 7], rows[p, 8],
                                         rows[p, 9], tau, weights)
            else:
                cov = np.zeros((3, 3))
            if rows[p, 12] != 0.0:  # cov + diag(slip variance, 0, 0), every entry
                for i in range(3):
                    for j in range(3):
                        cov[i, j] = cov[i, j] + (rows[p, 13] if i == 0 and j == 0 else 0.0)
            if np.any(cov != 0.0):
                factors[p] = factor_kernel(cov)
                which[p] = noisy
                noisy += 1
        for q in range(noisy):
            for i in range(particles.shape[0]):
                for c in range(3):
                    noise[q, i, c] = rng.standard_normal()
        move_pieces_kernel(particles, us, factors, noise, which, out)
else:  # pragma: no cover
    move_kernel = covariance_kernel = factor_kernel = move_pieces_kernel = plan_move_kernel = None
