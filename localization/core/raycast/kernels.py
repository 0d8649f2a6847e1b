"""Compiled (numba) kernels of the ray casters: the table build, and the per-sensor queries.

``LookupTableRayCaster.cast_numpy`` (``lookup_table.py``) is their numpy reference and fallback;
``test_range_table.py`` asserts the two equal. ``_march_from`` has the same arithmetic and
tie-breaking as ``ExactRayCaster`` (``exact.py``).
"""
from __future__ import annotations

import math

import numpy as np

try:  # numba is pinned in requirements.txt; numpy fallbacks keep the package importable without it
    from numba import int64, njit, uint64
    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - exercised only without numba
    HAVE_NUMBA = False

TABLE_MAX_UNITS = 65535  # uint16 fixed-point ranges
SAFE_MARGIN = math.sqrt(2.0) + 1e-6  # cells: see build_kernel

# consts (float64 array) shared by the query kernels:
C_INV_UNITS, C_MAX_CELLS, C_STEP, C_COS_STEP, C_SIN_STEP, C_REFINE = range(6)

if HAVE_NUMBA:
    @njit(cache=True, nogil=True, inline="always")
    def march_from(blocking, ox, oy, dx, dy, t0, max_cells):  # pragma: no cover - compiled
        """Amanatides–Woo in the padded blocking grid from ray parameter t0 (cells): the first
        entry into a blocking cell after t0 (t0 itself when the point there is in one), at most
        ``max_cells``. From t0 = 0 the same arithmetic and tie-breaking as ``ExactRayCaster``;
        the padding border stops every ray."""
        h, w = blocking.shape
        x = ox + t0 * dx
        y = oy + t0 * dy
        ix = int(math.floor(x))
        iy = int(math.floor(y))
        if ix < 0 or ix >= w or iy < 0 or iy >= h or blocking[iy, ix]:
            return t0
        inf = np.inf
        if dx > 0:
            step_x, t_dx = 1, abs(1.0 / dx)
            t_x = t0 + (ix + 1 - x) * t_dx
        elif dx < 0:
            step_x, t_dx = -1, abs(1.0 / dx)
            t_x = t0 + (x - ix) * t_dx
        else:
            step_x, t_dx, t_x = -1, inf, inf
        if dy > 0:
            step_y, t_dy = 1, abs(1.0 / dy)
            t_y = t0 + (iy + 1 - y) * t_dy
        elif dy < 0:
            step_y, t_dy = -1, abs(1.0 / dy)
            t_y = t0 + (y - iy) * t_dy
        else:
            step_y, t_dy, t_y = -1, inf, inf
        while True:
            if t_x < t_y:
                t = t_x
                ix += step_x
                t_x += t_dx
            else:
                t = t_y
                iy += step_y
                t_y += t_dy
            if t >= max_cells:
                return max_cells
            if ix < 0 or ix >= w or iy < 0 or iy >= h or blocking[iy, ix]:
                return t

    @njit(cache=True, nogil=True)
    def build_kernel(blocking, clearance, rows, cols, cos_k, sin_k, jump, max_cells, units_per_cell,
                      table):  # pragma: no cover
        """table[i, k] = range from the centre of free cell (rows[i], cols[i]) along bin k.

        Exact, but fast in open space: while the ray is far from every blocking cell it jumps
        (sphere tracing) by a step no blocking cell can be within, then finishes with the exact
        Amanatides–Woo march. ``clearance[iy, ix]``: a lower bound of the distance (cells) from
        the centre of cell (ix, iy) to the nearest blocking cell centre; a point in that cell is
        at least clearance − √2 from any point of any blocking cell (each point is within √2/2
        of its cell's centre), so a step shorter than that never skips one. Bins with ``jump[k]``
        False (the exact diagonals) are marched from the centre: their rays pass through lattice
        corners, where a march started elsewhere may break the tie between two diagonally
        touching wall cells otherwise than ``ExactRayCaster`` and make the table inconsistent
        between bins (which costs accuracy on the simulated trials: docs/performance.md)."""
        for i in range(rows.size):
            ox = cols[i] + 1.5  # +1: padding, +0.5: the cell centre
            oy = rows[i] + 1.5
            for k in range(cos_k.size):
                dx = cos_k[k]
                dy = sin_k[k]
                t = 0.0
                while t < max_cells and jump[k]:
                    safe = clearance[int(math.floor(oy + t * dy)), int(math.floor(ox + t * dx))] - SAFE_MARGIN
                    if safe < 2.0:  # close to a wall: the exact march takes over
                        break
                    t += safe
                t = march_from(blocking, ox, oy, dx, dy, t, max_cells) if t < max_cells else max_cells
                table[i, k] = np.uint16(min(t * units_per_cell + 0.5, 65535.0))

    @njit(cache=True, nogil=True)
    def bin_below(f, n_bins):  # pragma: no cover - compiled
        """The table bin k0 at or below the bin position f in [0, K) (K − 1 at most), unsigned: a read of a
        table row at it needs no negative-index test."""
        k0 = int64(f)
        return uint64(n_bins - 1 if k0 >= n_bins else k0)

    @njit(cache=True, nogil=True)
    def bin_above(k0, n_bins):  # pragma: no cover - compiled
        """The bin after the unsigned bin k0, mod K."""
        k1 = k0 + uint64(1)
        return uint64(0) if k1 >= uint64(n_bins) else k1

    @njit(cache=True, nogil=True)
    def wall_line_range(f, q0, q1, ub, vb, cb, sb, inv_units, step, cos_step, sin_step,
                        max_cells):  # pragma: no cover - compiled
        """One beam's range (cells, in [0, max_cells]), mode 2: on the wall line through the hit points of
        its two bins (table ranges q0, q1 in table units, ``inv_units`` cells each; ``step`` the bin
        width, rad), seen from the beam's origin (ub, vb) (cells from the cell centre, sensor frame; the
        beam along (cb, sb)); the nearest bin's range when the line is unusable (parallel, or a bin at
        the table's maximum)."""
        a = f - math.floor(f)
        along = ub * cb + vb * sb  # the beam origin's offset along the beam ...
        perp = vb * cb - ub * sb  # ... and across it
        near = (q0 if a < 0.5 else q1) * inv_units - along
        r0 = q0 * inv_units
        r1 = q1 * inv_units
        al = a * step  # the beam's angle past bin k0, within one bin: short series suffice
        al2 = al * al
        sa = al * (1.0 - al2 * (1.0 / 6.0) * (1.0 - al2 * (1.0 / 20.0)))
        ca = 1.0 - al2 * 0.5 * (1.0 - al2 * (1.0 / 12.0) * (1.0 - al2 * (1.0 / 30.0)))
        dxp = ca * along - sa * perp  # the offset in the frame of bin k0
        dyp = ca * perp + sa * along
        e_x = r1 * cos_step - r0  # hit point of bin k1 minus that of bin k0, same frame
        e_y = r1 * sin_step
        den = ca * e_y - sa * e_x
        lo = q0 if q0 < q1 else q1
        hi = q0 if q0 > q1 else q1
        use_line = (den > 1e-9) & (hi < 65535.0)
        den = den if use_line else 1.0
        line = ((r0 - dxp) * e_y + dyp * e_x) / den
        top = hi * inv_units + 1.0
        bottom = lo * inv_units - 1.0
        line = top if line > top else line
        line = bottom if line < bottom else line
        r = line if use_line else near
        r = 0.0 if r < 0.0 else r
        return max_cells if r > max_cells else r

    @njit(cache=True, nogil=True)
    def bin_range(mode, f, q0, q1, ub, vb, cb, sb, inv_units, max_cells):  # pragma: no cover - compiled
        """One beam's range (cells, in [0, max_cells]), mode 1: linear in the range between its two bins;
        mode 0: the nearest bin's (arguments as ``wall_line_range``)."""
        a = f - math.floor(f)
        along = ub * cb + vb * sb
        if mode == 1:  # linear in the range
            r = ((1.0 - a) * q0 + a * q1) * inv_units - along
        else:  # nearest bin
            r = (q0 if a < 0.5 else q1) * inv_units - along
        r = 0.0 if r < 0.0 else r
        return max_cells if r > max_cells else r

    @njit(cache=True, nogil=True)
    def beam_ranges(row, f0, u, v, du, dv, beam_f, beam_c, beam_s, consts, mode, fs, q0s, q1s,
                    out):  # pragma: no cover
        """Ranges (cells) of every beam seen from one sensor, into ``out`` (B,).

        ``row``: the table row of the sensor's cell; ``f0``: sensor heading in bins, in [0, K);
        ``beam_f``: beam angles in bins, in [0, K); (u, v): the sensor's offset from the cell
        centre in its own frame (ahead, left); (du[b], dv[b]): beam b's own origin offset from the
        sensor, same frame, in cells (a deskewed sweep; zeros otherwise); ``fs``, ``q0s``, ``q1s``: (B,) scratch. Three
        passes so the arithmetic pass has no gathers or branches and compiles to SIMD: bin
        positions, table reads, geometry (each beam's rule: ``wall_line_range``, ``bin_range``). The fused
        sensor kernel runs the same passes in its own body (``models.beam_kernels.fused_rows``)."""
        n_bins = row.size
        n_beams = beam_f.size
        inv_units = consts[C_INV_UNITS]
        max_cells = consts[C_MAX_CELLS]
        for b in range(n_beams):
            f = f0 + beam_f[b]
            fs[b] = f - n_bins if f >= n_bins else f
        for b in range(n_beams):
            k0 = bin_below(fs[b], n_bins)
            q0s[b] = row[k0]
            q1s[b] = row[bin_above(k0, n_bins)]
        if mode == 2:  # the wall line through the two bins' hit points; the nearest bin on a miss
            step, cos_step, sin_step = consts[C_STEP], consts[C_COS_STEP], consts[C_SIN_STEP]
            for b in range(n_beams):
                out[b] = wall_line_range(fs[b], q0s[b], q1s[b], u + du[b], v + dv[b], beam_c[b], beam_s[b],
                                         inv_units, step, cos_step, sin_step, max_cells)
        else:
            for b in range(n_beams):
                out[b] = bin_range(mode, fs[b], q0s[b], q1s[b], u + du[b], v + dv[b], beam_c[b], beam_s[b],
                                   inv_units, max_cells)

    @njit(cache=True, nogil=True)
    def refine(blocking, ox, oy, c, s, du, dv, beam_c, beam_s, consts, q0s, q1s, cells):  # pragma: no cover
        """Exact finish: march each beam (from the sensor at padded grid (ox, oy), heading
        cos/sin c, s, moved by the beam's own offset (du, dv) in the sensor frame) from
        ``consts[C_REFINE]`` cells short of the nearest of its estimate and its two bins' ranges,
        so a wall edge passing between the bins is resolved exactly. A start that lies in a wall
        already (the estimate overshot), or a beam origin in a wall, marches the beam from its origin."""
        margin = consts[C_REFINE]
        inv_units = consts[C_INV_UNITS]
        max_cells = consts[C_MAX_CELLS]
        for b in range(cells.size):
            near = min(q0s[b], q1s[b]) * inv_units
            t0 = min(cells[b], near) - margin
            t0 = t0 if t0 > 0.0 else 0.0
            bx, by = ox + c * du[b] - s * dv[b], oy + s * du[b] + c * dv[b]
            dx, dy = c * beam_c[b] - s * beam_s[b], s * beam_c[b] + c * beam_s[b]
            t = march_from(blocking, bx, by, dx, dy, t0, max_cells)
            ix, iy = int(math.floor(bx)), int(math.floor(by))
            if t0 > 0.0 and (t == t0 or not (0 <= ix < blocking.shape[1] and 0 <= iy < blocking.shape[0])
                             or blocking[iy, ix]):
                # the start lies in a wall already (the estimate overshot), or the beam's own origin does (a
                # deskew offset into a wall: it sees 0, as from the sensor): march it from its origin
                t = march_from(blocking, bx, by, dx, dy, 0.0, max_cells)
            cells[b] = t

    @njit(cache=True, nogil=True, inline="always")
    def locate(x, y, th, map_ox, map_oy, map_c, map_s, resolution, map_yaw, index, n_bins):  # pragma: no cover
        """World sensor pose -> (table row or -1, heading in bins f0 in [0, K), u, v, grid x,
        grid y, cos, sin of the grid heading). A sensor off the map, outside free space or with
        a non-finite pose gets row -1 (it sees 0)."""
        h, w = index.shape
        dx = x - map_ox
        dy = y - map_oy
        gx = (map_c * dx + map_s * dy) / resolution  # as OccupancyMap.world_to_grid_continuous
        gy = (-map_s * dx + map_c * dy) / resolution
        gth = th - map_yaw
        if not (gx >= 0.0 and gx < w and gy >= 0.0 and gy < h and math.isfinite(gth)):  # NaN fails too
            return -1, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0
        col = int(math.floor(gx))
        rr = int(math.floor(gy))
        cell = index[rr, col]
        if cell < 0:
            return -1, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0
        f0 = gth * (n_bins / (2.0 * np.pi))
        f0 -= n_bins * math.floor(f0 / n_bins)
        if f0 >= n_bins:
            f0 -= n_bins
        ex = gx - (col + 0.5)
        ey = gy - (rr + 0.5)
        c = math.cos(gth)
        s = math.sin(gth)
        return cell, f0, c * ex + s * ey, c * ey - s * ex, gx, gy, c, s

    @njit(cache=True, nogil=True)
    def cast_kernel(poses, map_ox, map_oy, map_c, map_s, resolution, map_yaw, index, table, blocking,
                     beam_f, beam_c, beam_s, consts, mode, out):  # pragma: no cover
        """out[i, b] = range (metres) of beam b from world sensor pose i."""
        n_bins = table.shape[1]
        n_beams = beam_f.size
        fs = np.empty(n_beams)
        q0s = np.empty(n_beams)
        q1s = np.empty(n_beams)
        cells = np.empty(n_beams)
        zeros = np.zeros(n_beams)  # no per-beam origin offsets
        for i in range(poses.shape[0]):
            cell, f0, u, v, gx, gy, c, s = locate(poses[i, 0], poses[i, 1], poses[i, 2], map_ox, map_oy, map_c,
                                                   map_s, resolution, map_yaw, index, n_bins)
            if cell < 0:
                for b in range(n_beams):
                    out[i, b] = 0.0
                continue
            beam_ranges(table[cell], f0, u, v, zeros, zeros, beam_f, beam_c, beam_s, consts, mode, fs, q0s, q1s,
                        cells)
            if consts[C_REFINE] > 0.0:
                refine(blocking, gx + 1.0, gy + 1.0, c, s, zeros, zeros, beam_c, beam_s, consts, q0s, q1s, cells)
            for b in range(n_beams):
                out[i, b] = cells[b] * resolution


if HAVE_NUMBA:
    @njit(cache=True, nogil=True)
    def chessboard_kernel(blocking, out):  # pragma: no cover - compiled
        """Two-pass chamfer with unit 8-neighbour steps: out = min(255, chessboard distance to the
        nearest blocking cell), as ``scipy.ndimage.distance_transform_cdt(~blocking, "chessboard")``."""
        h, w = blocking.shape
        for i in range(h):
            for j in range(w):
                if blocking[i, j]:
                    out[i, j] = 0
                    continue
                d = 255
                if i > 0:
                    for dj in (-1, 0, 1):
                        jj = j + dj
                        if 0 <= jj < w and out[i - 1, jj] + 1 < d:
                            d = out[i - 1, jj] + 1
                if j > 0 and out[i, j - 1] + 1 < d:
                    d = out[i, j - 1] + 1
                out[i, j] = d
        for i in range(h - 1, -1, -1):
            for j in range(w - 1, -1, -1):
                d = out[i, j]
                if d == 0:
                    continue
                if i < h - 1:
                    for dj in (-1, 0, 1):
                        jj = j + dj
                        if 0 <= jj < w and out[i + 1, jj] + 1 < d:
                            d = out[i + 1, jj] + 1
                if j < w - 1 and out[i, j + 1] + 1 < d:
                    d = out[i, j + 1] + 1
                out[i, j] = d
