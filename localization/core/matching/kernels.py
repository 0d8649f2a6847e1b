"""Compiled (numba) kernels of the correlative matcher, each with its numpy reference
(``test_reference.py`` asserts them equal).

Endpoints are given per candidate rotation j as integer cells ``cols[j, i]``, ``rows[j, i]`` of
beam i with the scan at the seed's position; a candidate (j, du, dv) shifts them by whole cells::

    score(j, du, dv) = (1/n) Σ_i grid[rows[j, i] + dv, cols[j, i] + du]      (0 off the grid)

The Gauss–Newton finish reads the signed distance bilinearly at the endpoints of a grid pose g
(``sdf_at``): endpoint (u, v) = (g_x, g_y) + R(g_φ) q_i, its cell (c0, r0) = ⌊(u, v) − ½⌋ clipped to
the grid, its fractions (f_x, f_y) clipped to [0, 1]::

    d   = (1 − f_y) ((1 − f_x) s00 + f_x s01) + f_y ((1 − f_x) s10 + f_x s11)
    ∂d/∂u = (1 − f_y)(s01 − s00) + f_y (s11 − s10),   ∂d/∂v = (1 − f_x)(s10 − s00) + f_x (s11 − s01)
    ∂d/∂φ = ∂d/∂u · ∂u/∂φ + ∂d/∂v · ∂v/∂φ
"""
from __future__ import annotations

import math

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
    """Mean grid value under the shifted endpoints of each candidate (j, du, dv), the beams summed in
    order (a running sum, as the compiled kernels add them: the same bits)."""
    h, w = grid.shape
    n = cols.shape[1]
    if n == 0:
        return np.zeros(len(cand_j))
    c = cols[cand_j] + np.asarray(cand_du)[:, None]
    r = rows[cand_j] + np.asarray(cand_dv)[:, None]
    inside = (c >= 0) & (c < w) & (r >= 0) & (r < h)
    vals = np.where(inside, grid[np.clip(r, 0, h - 1), np.clip(c, 0, w - 1)].astype(np.float64), 0.0)
    return np.cumsum(vals, axis=1)[:, -1] / n


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


def sdf_at_numpy(sdf, g, qg):
    """(d, ∂d/∂u, ∂d/∂v, ∂d/∂φ) (n,) each at the endpoints ``qg`` (n, 2; cells, base frame) of grid pose ``g``
    (module docstring; ``sdf`` float32, the differences of its cells taken in float32 as numpy does)."""
    cphi, sphi = math.cos(g[2]), math.sin(g[2])
    u = g[0] + cphi * qg[:, 0] - sphi * qg[:, 1]
    v = g[1] + sphi * qg[:, 0] + cphi * qg[:, 1]
    h, w = sdf.shape
    x, y = u - 0.5, v - 0.5
    c0 = np.clip(np.floor(x).astype(np.int64), 0, w - 2)
    r0 = np.clip(np.floor(y).astype(np.int64), 0, h - 2)
    fx, fy = np.clip(x - c0, 0, 1), np.clip(y - r0, 0, 1)
    s00, s01 = sdf[r0, c0], sdf[r0, c0 + 1]
    s10, s11 = sdf[r0 + 1, c0], sdf[r0 + 1, c0 + 1]
    d = (1 - fy) * ((1 - fx) * s00 + fx * s01) + fy * ((1 - fx) * s10 + fx * s11)
    gu = (1 - fy) * (s01 - s00) + fy * (s11 - s10)
    gv = (1 - fx) * (s10 - s00) + fx * (s11 - s01)
    du_dphi = -sphi * qg[:, 0] - cphi * qg[:, 1]
    dv_dphi = cphi * qg[:, 0] - sphi * qg[:, 1]
    return d, gu, gv, gu * du_dphi + gv * dv_dphi


# --------------------------------------------------------------------------------------------
# compiled kernels
# --------------------------------------------------------------------------------------------

if HAVE_NUMBA:
    @njit(cache=True, nogil=True)
    def _score_one(grid, cols, rows, j, du, dv, inside=False):  # pragma: no cover - compiled
        """Score of candidate (j, du, dv), its beams added in order; ``inside``: every shifted endpoint is
        known to lie on the grid, so no cell is tested."""
        h, w = grid.shape
        n = cols.shape[1]
        total = 0.0
        for i in range(n):
            c = cols[j, i] + du
            r = rows[j, i] + dv
            if inside or (0 <= c < w and 0 <= r < h):
                total += grid[r, c]
        return total / n if n > 0 else 0.0

    @njit(cache=True, nogil=True)
    def score_candidates(grid, cols, rows, cand_j, cand_du, cand_dv):  # pragma: no cover - compiled
        """``_score_one`` of each candidate, told ``inside`` when its rotation's box of endpoint cells,
        shifted, lies on the grid."""
        h, w = grid.shape
        count, n = cols.shape
        box = np.empty((count, 4), dtype=np.int64)  # per rotation: min col, max col, min row, max row
        for j in range(count):
            box[j, 0] = box[j, 2] = np.iinfo(np.int64).max
            box[j, 1] = box[j, 3] = np.iinfo(np.int64).min
            for i in range(n):
                box[j, 0] = min(box[j, 0], cols[j, i])
                box[j, 1] = max(box[j, 1], cols[j, i])
                box[j, 2] = min(box[j, 2], rows[j, i])
                box[j, 3] = max(box[j, 3], rows[j, i])
        out = np.empty(cand_j.shape[0])
        for m in range(cand_j.shape[0]):
            j, du, dv = cand_j[m], cand_du[m], cand_dv[m]
            inside = box[j, 0] + du >= 0 and box[j, 1] + du < w and box[j, 2] + dv >= 0 and box[j, 3] + dv < h
            out[m] = _score_one(grid, cols, rows, j, du, dv, inside)
        return out

    @njit(cache=True, nogil=True)
    def _score_block(grid, cols, rows, j, du0, nu, dv0, nv, acc):  # pragma: no cover - compiled
        """acc[b, a] = the total of ``_score_one(…, j, du0 + a, dv0 + b)`` for the block's nu × nv shifts,
        beam by beam: each beam adds its k × k patch of the grid row by row (the cells a row of shifts reads
        lie side by side), and each total still sums its beams in order, as ``_score_one`` does."""
        h, w = grid.shape
        for b in range(nv):
            for a in range(nu):
                acc[b, a] = 0.0
        for i in range(cols.shape[1]):
            c0 = cols[j, i] + du0
            r0 = rows[j, i] + dv0
            if 0 <= c0 and c0 + nu <= w and 0 <= r0 and r0 + nv <= h:  # the patch inside the grid
                for b in range(nv):
                    for a in range(nu):
                        acc[b, a] += grid[r0 + b, c0 + a]
                continue
            for b in range(nv):
                r = r0 + b
                if 0 <= r < h:
                    for a in range(nu):
                        c = c0 + a
                        if 0 <= c < w:
                            acc[b, a] += grid[r, c]

    @njit(cache=True, nogil=True)
    def branch_and_bound(grid, cols, rows, cand_j, cand_du, cand_dv, bounds, k, window):  # pragma: no cover
        """Coarse blocks sorted by their bound (descending): expand each block (its k × k fine
        shifts, within ±window) until the next bound cannot beat the best fine score. The shifts are
        compared in the order du, then dv, so the first of equal scores wins.
        Returns (best score, j, du, dv)."""
        best, bj, bdu, bdv = -1.0, 0, 0, 0
        n = cols.shape[1]
        acc = np.empty((k, k))
        for m in range(cand_j.shape[0]):
            if bounds[m] <= best:
                break
            j = cand_j[m]
            du0, dv0 = cand_du[m], cand_dv[m]
            nu = min(du0 + k, window + 1) - du0
            nv = min(dv0 + k, window + 1) - dv0
            _score_block(grid, cols, rows, j, du0, nu, dv0, nv, acc)
            for a in range(nu):
                for b in range(nv):
                    s = acc[b, a] / n if n > 0 else 0.0
                    if s > best:
                        best, bj, bdu, bdv = s, j, du0 + a, dv0 + b
        return best, bj, bdu, bdv

    @njit(cache=True, nogil=True)
    def _sdf_at_kernel(sdf, g0, g1, g2, qg, d, gu, gv, gphi):  # pragma: no cover - compiled
        """``sdf_at_numpy`` into (n,) arrays, one endpoint at a time: the same operations in the same order.
        False (the arrays unfinished) at an endpoint that is not finite: numpy's reference takes those."""
        h, w = sdf.shape
        cphi = math.cos(g2)
        sphi = math.sin(g2)
        for i in range(qg.shape[0]):
            qx = qg[i, 0]
            qy = qg[i, 1]
            x = (g0 + cphi * qx - sphi * qy) - 0.5
            y = (g1 + sphi * qx + cphi * qy) - 0.5
            if not (math.isfinite(x) and math.isfinite(y)):
                return False
            c0 = min(max(np.int64(math.floor(x)), 0), w - 2)
            r0 = min(max(np.int64(math.floor(y)), 0), h - 2)
            fx = min(max(x - c0, 0.0), 1.0)
            fy = min(max(y - r0, 0.0), 1.0)
            s00 = sdf[r0, c0]
            s01 = sdf[r0, c0 + 1]
            s10 = sdf[r0 + 1, c0]
            s11 = sdf[r0 + 1, c0 + 1]
            d[i] = (1 - fy) * ((1 - fx) * np.float64(s00) + fx * np.float64(s01)) + fy * (
                (1 - fx) * np.float64(s10) + fx * np.float64(s11))
            du = (1 - fy) * np.float64(s01 - s00) + fy * np.float64(s11 - s10)
            dv = (1 - fx) * np.float64(s10 - s00) + fx * np.float64(s11 - s01)
            gu[i] = du
            gv[i] = dv
            gphi[i] = du * (-sphi * qx - cphi * qy) + dv * (cphi * qx - sphi * qy)
        return True

    def sdf_at(sdf, g, qg):
        """``sdf_at_numpy``, compiled: one pass over the endpoints, the same values bit for bit (float64
        endpoints; others, whose arithmetic numpy does in their own type, go to numpy)."""
        n = qg.shape[0]
        d, gu, gv, gphi = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
        if qg.dtype == np.float64 and _sdf_at_kernel(sdf, float(g[0]), float(g[1]), float(g[2]),
                                                     np.ascontiguousarray(qg), d, gu, gv, gphi):
            return d, gu, gv, gphi
        return sdf_at_numpy(sdf, g, qg)
else:  # pragma: no cover
    score_candidates = score_candidates_numpy
    sdf_at = sdf_at_numpy

    def branch_and_bound(grid, cols, rows, cand_j, cand_du, cand_dv, bounds, k, window):
        return branch_and_bound_numpy(grid, cols, rows, cand_j, cand_du, cand_dv, bounds, k, window)
