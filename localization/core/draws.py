"""Standard normal deviates for the filter's noise, drawn by compiled code.

    standard_normal_into(rng, out)   out ← rng.standard_normal(out.shape), in place

numba runs numpy's own algorithm (the ziggurat over the generator's bit stream) on numpy's ``Generator``: the
values are numpy's bit for bit, and the generator is left in the very state numpy leaves it in, so every seeded
run draws what it drew before. The compiled loop costs about half of numpy's per deviate on this project's
machines (docs/performance.md); a call has a fixed cost of its own (the generator handed to compiled code), so
small arrays, and generators numba does not take, go to numpy. ``test/test_draws.py`` asserts the two equal.
"""
from __future__ import annotations

import numpy as np

try:  # numba is pinned; numpy draws the same values without it
    from numba import njit
except ImportError:  # pragma: no cover
    njit = None

COMPILED_MIN_SIZE = 1024  # deviates: below, numpy's call is the cheaper (the values are the same)

if njit is not None:
    @njit(cache=True, nogil=True)
    def _fill_standard_normal(rng, flat):  # pragma: no cover - compiled
        for i in range(flat.size):
            flat[i] = rng.standard_normal()
else:  # pragma: no cover
    _fill_standard_normal = None


def standard_normal_into(rng: np.random.Generator, out: np.ndarray) -> np.ndarray:
    """Fill ``out`` (float64, C-contiguous, as ``Generator.standard_normal(out=...)`` takes it) with
    ``rng.standard_normal(out.shape)``'s values, in place; returns it."""
    if (_fill_standard_normal is None or out.size < COMPILED_MIN_SIZE or not out.flags.c_contiguous
            or not isinstance(rng.bit_generator, np.random.PCG64)):
        return rng.standard_normal(out=out)  # numpy's own (it refuses what it cannot fill)
    _fill_standard_normal(rng, out.reshape(-1))
    return out
