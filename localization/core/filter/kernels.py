"""The particle filter's compiled passes outside the sensor kernel (numba; ``mcl.py`` holds their numpy references,
asserted equal in ``test/test_filter_kernels.py``):

    weigh_kernel      log w ← log w + log f, normalised in log space (log-sum-exp), and w = exp(log w) with
                      Σ w² for the effective sample size: three passes over the N weights, no temporaries
    estimate_kernel   the weighted mean x, y, the circular mean θ and the weighted covariance (θ wrapped):
                      three passes over the N particles (the largest log weight, the sums, the covariance)

They write into arrays the filter keeps from scan to scan (``MonteCarloLocalizer``), so a sensor update in
steady state allocates nothing that grows with the particles. Sums run particle by particle, where numpy
sums pairwise: the results agree to rounding (about 1e-15 relative).
"""
from __future__ import annotations

import math

import numpy as np

try:  # numba is pinned; the numpy references in mcl.py serve without it
    from numba import njit
except ImportError:  # pragma: no cover
    njit = None

if njit is not None:
    @njit(cache=True, nogil=True)
    def weigh_kernel(log_weights, log_factor, out_log_weights, out_weights):  # pragma: no cover - compiled
        """out_log_weights = log_weights + log_factor − their log-sum-exp; out_weights = exp(out_log_weights).
        Returns (the log normaliser, Σ w²); (NaN, 0) when every particle gets weight 0 or a NaN appears (the
        outputs are then not to be used). ``out_log_weights`` may be ``log_weights`` itself."""
        n = log_weights.size
        peak = -np.inf
        for i in range(n):
            c = log_weights[i] + log_factor[i]
            if math.isnan(c):
                return np.nan, 0.0
            out_log_weights[i] = c
            if c > peak:
                peak = c
        if not math.isfinite(peak):
            return np.nan, 0.0
        total = 0.0
        for i in range(n):
            total += math.exp(out_log_weights[i] - peak)
        norm = peak + math.log(total)
        squares = 0.0
        for i in range(n):
            v = out_log_weights[i] - norm
            out_log_weights[i] = v
            w = math.exp(v)
            out_weights[i] = w
            squares += w * w
        return norm, squares

    @njit(cache=True, nogil=True)
    def estimate_kernel(particles, log_weights, mean, cov):  # pragma: no cover - compiled
        """mean (3,) = the weighted mean x, y and circular mean θ; cov (3, 3) = the weighted covariance about it
        (θ differences wrapped to (−π, π]), the weights exp(log_weights) normalised."""
        n = particles.shape[0]
        peak = -np.inf
        for i in range(n):
            if log_weights[i] > peak:
                peak = log_weights[i]
        sw = sx = sy = ss = sc = 0.0
        for i in range(n):
            e = math.exp(log_weights[i] - peak)
            sw += e
            sx += e * particles[i, 0]
            sy += e * particles[i, 1]
            ss += e * math.sin(particles[i, 2])
            sc += e * math.cos(particles[i, 2])
        mx = sx / sw
        my = sy / sw
        mth = math.atan2(ss, sc)
        mean[0] = mx
        mean[1] = my
        mean[2] = mth
        two_pi = 2.0 * np.pi
        cxx = cxy = cxt = cyy = cyt = ctt = 0.0
        for i in range(n):
            w = math.exp(log_weights[i] - peak) / sw
            dx = particles[i, 0] - mx
            dy = particles[i, 1] - my
            dt = particles[i, 2] - mth + np.pi  # as geometry.wrap_angle; the modulo only outside [0, 2π)
            dt = dt - np.pi if 0.0 <= dt < two_pi else dt % two_pi - np.pi
            if dt <= -np.pi:
                dt += two_pi
            cxx += w * dx * dx
            cxy += w * dx * dy
            cxt += w * dx * dt
            cyy += w * dy * dy
            cyt += w * dy * dt
            ctt += w * dt * dt
        cov[0, 0] = cxx
        cov[0, 1] = cov[1, 0] = cxy
        cov[0, 2] = cov[2, 0] = cxt
        cov[1, 1] = cyy
        cov[1, 2] = cov[2, 1] = cyt
        cov[2, 2] = ctt
else:  # pragma: no cover
    weigh_kernel = estimate_kernel = None
