"""Compiled (numba) kernels of the correlative matcher, each with its numpy reference
(``test_reference.py`` asserts them equal).

Endpoints are given per candidate rotation j as integer cells ``cols[j, i]``, ``rows[j, i]`` of
beam i with the scan at the seed's position; a candidate (j, du, dv) shifts them by whole cells::

    score(j, du, dv) = (1/n) Σ_i grid[rows[j, i] + dv, cols[j, i] + du]      (0 off the grid)
"""
from __future__ import annotations

import numpy as np

try:  # numba is pinned in requirements.txt; numpy fallbacks keep the package importable without it
    from numba import njit
    HAVE_NUMBA = True
except ImportError:  # pragma: no cover
    HAVE_NUMBA = False


# --------------------------------------------------------------------------------------------
# numpy references
# --------------------------------------------------------------------------------------------


def score_candidates_numpy(grid, cols, rows, cand_j, cand_du, cand_dv) -> np.ndarray:
    """Mean grid value under the shifted endpoints of each candidate (j, du, dv)."""
    h, w = grid.shape
    n = cols.shape[1]
    if n == 0:
        return np.zeros(len(cand_j))
    c = cols[cand_j] + np.asarray(cand_du)[:, None]
    r = rows[cand_j] + np.asarray(cand_dv)[:, None]
    inside = (c >= 0) & (c < w) & (r >= 0) & (r < h)
    vals = np.where(inside, grid[np.clip(r, 0, h - 1), np.clip(c, 0, w - 1)].astype(np.float64), 0.0)
    return vals.sum(axis=1) / n


def branch_and_bound_numpy(grid, cols, rows, cand_j, cand_du, cand_dv, bounds, k, window):
    """Reference of ``branch_and_bound``: every fine shift of every coarse block, exhaustively.
    Returns (best score, j, du, dv)."""
    best = (-1.0, 0, 0, 0)
    for j, du0, dv0 in zip(cand_j, cand_du, cand_dv):
        du = np.arange(du0, min(du0 + k, window + 1))
        dv = np.arange(dv0, min(dv0 + k, window + 1))
        DU, DV = np.meshgrid(du, dv, indexing="ij")
        s = score_candidates_numpy(grid, cols, rows, np.full(DU.size, j), DU.ravel(), DV.ravel())
        i = int(np.argmax(s))
        if s[i] > best[0]:
            best = (float(s[i]), int(j), int(DU.ravel()[i]), int(DV.ravel()[i]))
    return best


# --------------------------------------------------------------------------------------------
# compiled kernels
# --------------------------------------------------------------------------------------------

if HAVE_NUMBA:
    @njit(cache=True, nogil=True)
    def _score_one(grid, cols, rows, j, du, dv):  # pragma: no cover - compiled
        h, w = grid.shape
        n = cols.shape[1]
        total = 0.0
        for i in range(n):
            c = cols[j, i] + du
            r = rows[j, i] + dv
            if 0 <= c < w and 0 <= r < h:
                total += grid[r, c]
        return total / n if n > 0 else 0.0

    @njit(cache=True, nogil=True)
    def score_candidates(grid, cols, rows, cand_j, cand_du, cand_dv):  # pragma: no cover - compiled
        out = np.empty(cand_j.shape[0])
        for m in range(cand_j.shape[0]):
            out[m] = _score_one(grid, cols, rows, cand_j[m], cand_du[m], cand_dv[m])
        return out

    @njit(cache=True, nogil=True)
    def branch_and_bound(grid, cols, rows, cand_j, cand_du, cand_dv, bounds, k, window):  # pragma: no cover
        """Coarse blocks sorted by their bound (descending): expand each block (its k × k fine
        shifts, within ±window) until the next bound cannot beat the best fine score.
        Returns (best score, j, du, dv)."""
        best, bj, bdu, bdv = -1.0, 0, 0, 0
        for m in range(cand_j.shape[0]):
            if bounds[m] <= best:
                break
            j = cand_j[m]
            for du in range(cand_du[m], min(cand_du[m] + k, window + 1)):
                for dv in range(cand_dv[m], min(cand_dv[m] + k, window + 1)):
                    s = _score_one(grid, cols, rows, j, du, dv)
                    if s > best:
                        best, bj, bdu, bdv = s, j, du, dv
        return best, bj, bdu, bdv
else:  # pragma: no cover
    score_candidates = score_candidates_numpy

    def branch_and_bound(grid, cols, rows, cand_j, cand_du, cand_dv, bounds, k, window):
        return branch_and_bound_numpy(grid, cols, rows, cand_j, cand_du, cand_dv, bounds, k, window)
