"""Systematic (low-variance) resampling.

For normalised weights w (cumulative sums c_i = Σ_{k≤i} w_k, the last set to exactly 1) and one
uniform draw u0 ∈ [0, 1), position j of n picks

    i_j = min{ i : c_i > (u0 + j) / n }

so every particle with weight w is kept ⌊n·w⌋ or ⌈n·w⌉ times, with a single random number.
``systematic_indices`` is the numpy form (any output count: resampling and resizing);
``resample_kernel`` the compiled O(N) merge walk that also copies and roughens the particles,
asserted equal to the numpy form in the tests.
"""
from __future__ import annotations

import numpy as np

try:  # a compiled single pass when numba is there (pinned); the numpy code otherwise
    from numba import njit
except ImportError:  # pragma: no cover
    njit = None

NO_NOISE = np.zeros((0, 3))


def systematic_indices(weights, n: int, u0: float) -> np.ndarray:
    """Systematic (low-variance) resampling: the index drawn for each of ``n`` positions
    (u0 + j) / n, u0 in [0, 1), from normalised ``weights`` (any length)."""
    cumulative = np.cumsum(weights)
    cumulative[-1] = 1.0
    idx = np.searchsorted(cumulative, (u0 + np.arange(n)) / n, side="right")
    return np.minimum(idx, len(cumulative) - 1)

if njit is not None:
    @njit(cache=True, nogil=True)
    def resample_kernel(particles, weights, u0, noise, roughening, out):  # pragma: no cover - compiled
        """Systematic resampling by a merge walk: out[j] = particles[i_j] (+ noise[j] · roughening,
        θ wrapped), i_j = the first i with cumsum(weights)[i] > (u0 + j) / n (the last entry taken
        as 1), as ``np.searchsorted(..., side="right")``. ``noise`` of length 0: no roughening."""
        n = particles.shape[0]
        rough = noise.shape[0] == n
        two_pi = 2.0 * np.pi
        i = 0
        cumulative = 1.0 if n == 1 else weights[0]
        for j in range(n):
            position = (u0 + j) / n
            while i < n - 1 and cumulative <= position:
                i += 1
                cumulative = 1.0 if i == n - 1 else cumulative + weights[i]
            if rough:
                out[j, 0] = particles[i, 0] + noise[j, 0] * roughening[0]
                out[j, 1] = particles[i, 1] + noise[j, 1] * roughening[1]
                w = particles[i, 2] + noise[j, 2] * roughening[2] + np.pi  # the modulo only outside [0, 2π)
                w = w - np.pi if 0.0 <= w < two_pi else w % two_pi - np.pi
                out[j, 2] = w + two_pi if w <= -np.pi else w  # as geometry.wrap_angle
            else:
                out[j, 0] = particles[i, 0]
                out[j, 1] = particles[i, 1]
                out[j, 2] = particles[i, 2]
else:  # pragma: no cover
    resample_kernel = None
