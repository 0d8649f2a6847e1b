"""Lookup-table ray casting: expected ranges precomputed over (free cell, heading bin).

Real time at thousands of particles needs a ray cast whose cost is a memory read, not a march
through the grid. ``LookupTableRayCaster`` precomputes, for every *free* cell of the map (only
free cells matter: a sensor in any other cell sees 0, see ``ray_casting``) and each of
``theta_bins`` headings θ_k = 2πk / K in the grid frame, the exact (Amanatides–Woo) range from
the cell centre. The table is stored compactly:

- ``index``: int32 (H, W) grid, the table row of each free cell, -1 elsewhere;
- ``table``: uint16 (F, K), ranges in fixed point (``units_per_cell`` units per cell, so the
  longest range, ``max_cells``, uses the whole 16 bits: 1/327 cell at 10 m). Stata basement:
  310k free cells x 144 bins = 85 MB. One row holds every heading of one cell, so the beams of
  one particle read a few consecutive cache lines.

A query at a continuous sensor pose (x, y, θ) reads the two bins around each beam from the row
of the cell the sensor is in, and intersects the beam — cast from the sensor's true position in
the cell, not the centre — with the line through the two bins' hit points: exact for a straight
wall whatever the incidence, and continuous in the pose everywhere else (only where a bin sees
nothing within max range is the nearest bin taken). Against ``ExactRayCaster`` on the Stata
basement (uniform random free poses and headings, 60 beams over 270°, 10 m) with 144 bins:
median |Δ| 0.001 cell, 95th percentile 2.3 cells (3.2 with 112 bins); the residue is beams near
wall edges and small features between two bins, and pixel-staircase walls.

Continuity matters more to the filter than those percentiles: taking the nearest bin across a
wall edge (sharper on random poses) made the cross-track error of the simulated Stata trials
(``localization-demo``) ~5 mm worse than smooth interpolation. Still, in those simulations — whose
scans are exact casts of this very grid plus 1 cm noise — the table alone trails the exact caster:
mean CT 18.7 / 19.7 / 24.9 mm against 11.3 / 13.7 / 20.2 mm on the three trials (real racecar
bags: the same scan–map agreement). The *exact finish* (``refine``, ray caster
``lookup_table_exact``) closes that gap (11.3 / 13.4 / 20.1 mm): each beam is marched through
the grid from one cell short of the nearest of its estimate and its two bins' ranges, so 99% of
beams equal ``ExactRayCaster``'s; it costs ~4x the lookup (2000 x 100 sensor update ~7 ms
instead of ~1.7 ms, against ~90 ms with ``DistanceTransformRayCaster``).

The table is built by a compiled (numba) Amanatides–Woo marcher with the same arithmetic as
``ExactRayCaster`` (so it matches it at the cell centres), ~11 M rays/s on one core: 4-5 s for
the Stata basement. It is cached on disk (``$LOCALIZATION_CACHE_DIR``, else
``~/.cache/localization``) under a key of the map's content digest, max range, bin count and
format version; files are written atomically, so a restart loads it in ~0.1 s. Without numba
everything still works through numpy (slowly: the build then uses ``ExactRayCaster``).

``log_likelihood_sums`` is the fused sensor-model kernel used by ``SensorModel.log_likelihood``
for this caster: laser offset → grid pose → table row → interpolated range → table index →
log p(z|d) sum, per particle, with no (N, B) temporaries.
"""
from __future__ import annotations

import json
import logging
import math
import os
import tempfile
import time
import weakref
import zipfile
from pathlib import Path

import numpy as np

from .occupancy_map import OccupancyMap
from .ray_casting import ExactRayCaster, RayCaster

try:  # numba is pinned in requirements.txt; numpy fallbacks keep the package importable without it
    import numba
    from numba import njit
    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - exercised only without numba
    numba = None
    HAVE_NUMBA = False

FORMAT_VERSION = 2  # 2: tables of the sphere-tracing build before the diagonal fix are not reused
DEFAULT_THETA_BINS = 144
TABLE_MAX_UNITS = 65535  # uint16

log = logging.getLogger(__name__)

# Tables alive in this process, by cache file name: a second caster for the same map (a map
# message sent again, another filter) shares the table instead of reading a second copy.
_LIVE_TABLES: "weakref.WeakValueDictionary[str, np.ndarray]" = weakref.WeakValueDictionary()


def default_cache_dir() -> Path:
    """``$LOCALIZATION_CACHE_DIR``, else ``$XDG_CACHE_HOME/localization`` (``~/.cache/localization``),
    as ``datasets.cache_dir``."""
    env = os.environ.get("LOCALIZATION_CACHE_DIR")
    if env:
        return Path(env).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "localization"


def cache_file_name(occupancy_map: OccupancyMap, max_range: float, theta_bins: int) -> str:
    """The cache key as a file name: map content digest + max range + bins + format version."""
    return f"range_table_v{FORMAT_VERSION}_{occupancy_map.digest}_r{float(max_range):.9g}_k{int(theta_bins)}.npz"


# ---------------------------------------------------------------------------------------------
# compiled kernels (numba); ``LookupTableRayCaster.cast_numpy`` is their numpy counterpart
# ---------------------------------------------------------------------------------------------
SAFE_MARGIN = math.sqrt(2.0) + 1e-6  # cells: see _build_kernel
BUILD_THREADS = 4  # at most: the table is built once per map, with every core the machine has

# consts (float64 array) shared by the query kernels:
C_INV_UNITS, C_MAX_CELLS, C_STEP, C_COS_STEP, C_SIN_STEP, C_REFINE = range(6)

if HAVE_NUMBA:
    @njit(cache=True, nogil=True, inline="always")
    def _march_from(blocking, ox, oy, dx, dy, t0, max_cells):  # pragma: no cover - compiled
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
    def _build_kernel(blocking, clearance, rows, cols, cos_k, sin_k, jump, max_cells, units_per_cell,
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
        between bins (measured: mean CT error of the simulated trials 0.03 m instead of 0.02)."""
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
                t = _march_from(blocking, ox, oy, dx, dy, t, max_cells) if t < max_cells else max_cells
                table[i, k] = np.uint16(min(t * units_per_cell + 0.5, 65535.0))

    @njit(cache=True, nogil=True)
    def _beam_ranges(row, f0, u, v, beam_f, beam_c, beam_s, consts, mode, fs, q0s, q1s, out):  # pragma: no cover
        """Ranges (cells) of every beam seen from one sensor, into ``out`` (B,).

        ``row``: the table row of the sensor's cell; ``f0``: sensor heading in bins, in [0, K);
        ``beam_f``: beam angles in bins, in [0, K); (u, v): the sensor's offset from the cell
        centre in its own frame (ahead, left); ``fs``, ``q0s``, ``q1s``: (B,) scratch. Three
        passes so the arithmetic pass has no gathers or branches and compiles to SIMD: bin
        positions, table reads, geometry."""
        n_bins = row.size
        n_beams = beam_f.size
        inv_units = consts[C_INV_UNITS]
        max_cells = consts[C_MAX_CELLS]
        for b in range(n_beams):
            f = f0 + beam_f[b]
            fs[b] = f - n_bins if f >= n_bins else f
        for b in range(n_beams):
            k0 = int(fs[b])
            k0 = n_bins - 1 if k0 >= n_bins else k0
            k1 = k0 + 1
            k1 = 0 if k1 >= n_bins else k1
            q0s[b] = row[k0]
            q1s[b] = row[k1]
        if mode == 2:  # the wall line through the two bins' hit points; the nearest bin on a miss
            step = consts[C_STEP]
            cos_step = consts[C_COS_STEP]
            sin_step = consts[C_SIN_STEP]
            for b in range(n_beams):
                f = fs[b]
                a = f - math.floor(f)
                q0 = q0s[b]
                q1 = q1s[b]
                cb = beam_c[b]
                sb = beam_s[b]
                along = u * cb + v * sb  # the sensor's offset along the beam ...
                perp = v * cb - u * sb  # ... and across it
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
                out[b] = max_cells if r > max_cells else r
        else:
            for b in range(n_beams):
                f = fs[b]
                a = f - math.floor(f)
                along = u * beam_c[b] + v * beam_s[b]
                if mode == 1:  # linear in the range
                    r = ((1.0 - a) * q0s[b] + a * q1s[b]) * inv_units - along
                else:  # nearest bin
                    r = (q0s[b] if a < 0.5 else q1s[b]) * inv_units - along
                r = 0.0 if r < 0.0 else r
                out[b] = max_cells if r > max_cells else r

    @njit(cache=True, nogil=True)
    def _refine(blocking, ox, oy, c, s, beam_c, beam_s, consts, q0s, q1s, cells):  # pragma: no cover
        """Exact finish: march each beam (from the sensor at padded grid (ox, oy), heading
        cos/sin c, s) from ``consts[C_REFINE]`` cells short of the nearest of its estimate and
        its two bins' ranges, so a wall edge passing between the bins is resolved exactly."""
        margin = consts[C_REFINE]
        inv_units = consts[C_INV_UNITS]
        max_cells = consts[C_MAX_CELLS]
        for b in range(cells.size):
            near = min(q0s[b], q1s[b]) * inv_units
            t0 = min(cells[b], near) - margin
            cells[b] = _march_from(blocking, ox, oy, c * beam_c[b] - s * beam_s[b], s * beam_c[b] + c * beam_s[b],
                                   t0 if t0 > 0.0 else 0.0, max_cells)

    @njit(cache=True, nogil=True, inline="always")
    def _locate(x, y, th, map_ox, map_oy, map_c, map_s, resolution, map_yaw, index, n_bins):  # pragma: no cover
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
    def _cast_kernel(poses, map_ox, map_oy, map_c, map_s, resolution, map_yaw, index, table, blocking,
                     beam_f, beam_c, beam_s, consts, mode, out):  # pragma: no cover
        """out[i, b] = range (metres) of beam b from world sensor pose i."""
        n_bins = table.shape[1]
        n_beams = beam_f.size
        fs = np.empty(n_beams)
        q0s = np.empty(n_beams)
        q1s = np.empty(n_beams)
        cells = np.empty(n_beams)
        for i in range(poses.shape[0]):
            cell, f0, u, v, gx, gy, c, s = _locate(poses[i, 0], poses[i, 1], poses[i, 2], map_ox, map_oy, map_c,
                                                   map_s, resolution, map_yaw, index, n_bins)
            if cell < 0:
                for b in range(n_beams):
                    out[i, b] = 0.0
                continue
            _beam_ranges(table[cell], f0, u, v, beam_f, beam_c, beam_s, consts, mode, fs, q0s, q1s, cells)
            if consts[C_REFINE] > 0.0:
                _refine(blocking, gx + 1.0, gy + 1.0, c, s, beam_c, beam_s, consts, q0s, q1s, cells)
            for b in range(n_beams):
                out[i, b] = cells[b] * resolution

    @njit(cache=True, nogil=True)
    def _log_likelihood_kernel(particles, off_x, off_y, off_th, map_ox, map_oy, map_c, map_s, resolution, map_yaw,
                               occupied, index, table, blocking, beam_f, beam_c, beam_s, consts, mode,
                               cells_per_metre, z_max, log_rows, squash_factor, out):  # pragma: no cover
        """out[i] = Σ_b log p(z_b | d_b(particle i)) / squash_factor; −inf for particles off the map
        or in an occupied cell. ``log_rows[b]`` is the log table row of the measured z_b."""
        n_bins = table.shape[1]
        h, w = occupied.shape
        n_beams = beam_f.size
        fs = np.empty(n_beams)
        q0s = np.empty(n_beams)
        q1s = np.empty(n_beams)
        cells = np.empty(n_beams)
        d_index = np.empty(n_beams, dtype=np.int64)
        blind = 0.0  # a sensor outside free space sees 0 on every beam
        for b in range(n_beams):
            blind += log_rows[b, 0]
        for i in range(particles.shape[0]):
            px = particles[i, 0]
            py = particles[i, 1]
            pth = particles[i, 2]
            dx = px - map_ox
            dy = py - map_oy
            gx = (map_c * dx + map_s * dy) / resolution
            gy = (-map_s * dx + map_c * dy) / resolution
            if not (gx >= 0.0 and gx < w and gy >= 0.0 and gy < h):  # off the map (or NaN)
                out[i] = -np.inf
                continue
            if occupied[int(math.floor(gy)), int(math.floor(gx))]:
                out[i] = -np.inf
                continue
            c = math.cos(pth)
            s = math.sin(pth)
            cell, f0, u, v, sx, sy, sc, ss = _locate(px + c * off_x - s * off_y, py + s * off_x + c * off_y,
                                                     pth + off_th, map_ox, map_oy, map_c, map_s, resolution,
                                                     map_yaw, index, n_bins)
            if cell < 0:
                out[i] = blind / squash_factor
                continue
            _beam_ranges(table[cell], f0, u, v, beam_f, beam_c, beam_s, consts, mode, fs, q0s, q1s, cells)
            if consts[C_REFINE] > 0.0:
                _refine(blocking, sx + 1.0, sy + 1.0, sc, ss, beam_c, beam_s, consts, q0s, q1s, cells)
            for b in range(n_beams):
                d = (cells[b] * resolution) * cells_per_metre  # metres, then as SensorModel.to_cells
                d = z_max if d > z_max else d
                d_index[b] = int(np.rint(d))
            total = 0.0
            for b in range(n_beams):
                total += log_rows[b, d_index[b]]
            out[i] = total / squash_factor


# ---------------------------------------------------------------------------------------------
# the caster
# ---------------------------------------------------------------------------------------------
INTERPOLATIONS = {"nearest": 0, "linear": 1, "line": 2}


class LookupTableRayCaster(RayCaster):
    """Ranges from a precomputed (free cell x heading bin) table; see the module docstring.

    ``interpolation`` between the two heading bins around a beam:

    - ``"line"`` (default): the beam, cast from the sensor's true position in its cell, is
      intersected with the line through the two bins' hit points: exact for a straight wall at
      any incidence, and continuous in the pose across wall edges too (which the filter's
      accuracy needs more than a sharp but bin-quantised edge). Where a bin sees nothing (max
      range), the nearest bin is used;
    - ``"linear"``: linear in the range; ``"nearest"``: the nearest bin. Both subtract the
      sensor's offset from the cell centre along the beam.

    ``refine`` > 0 (cells) turns on an *exact finish*: each beam is then marched through the
    grid from ``refine`` cells short of the nearest of its estimate and its two bins' ranges, so
    straight walls, staircase walls and edges between the bins all come out as with
    ``ExactRayCaster`` (except a thin obstacle both bins missed). About 4x the cost of the
    lookup; it buys 5-7 mm of cross-track accuracy in simulations whose scans are exact casts of
    the same grid, nothing measurable on real scans (see the module docstring).

    ``table``: a ready (F, theta_bins) uint16 table, else it is built here; use ``for_map`` to
    go through the disk cache."""

    def __init__(self, occupancy_map: OccupancyMap, max_range: float, theta_bins: int = DEFAULT_THETA_BINS,
                 table: np.ndarray | None = None, interpolation: str = "line", refine: float = 0.0,
                 use_numba: bool = HAVE_NUMBA):
        super().__init__(occupancy_map, max_range)
        theta_bins = int(theta_bins)
        if theta_bins < 8:
            raise ValueError(f"theta_bins must be >= 8, got {theta_bins}")
        if interpolation not in INTERPOLATIONS:
            raise ValueError(f"unknown interpolation {interpolation!r} ({', '.join(INTERPOLATIONS)})")
        if not (math.isfinite(refine) and refine >= 0):
            raise ValueError(f"refine must be a number of cells >= 0, got {refine}")
        self.theta_bins = theta_bins
        self.interpolation = interpolation
        self.refine = float(refine)
        self.use_numba = bool(use_numba) and HAVE_NUMBA
        free = occupancy_map.free
        self.num_free = int(np.count_nonzero(free))
        self.index = np.full(free.shape, -1, dtype=np.int32)
        self.index[free] = np.arange(self.num_free, dtype=np.int32)
        self.units_per_cell = TABLE_MAX_UNITS / self.max_cells
        self.loaded_from_cache = False  # for_map: the table came from memory or disk
        self.table_source = "given" if table is not None else "built"
        self.cache_path: Path | None = None
        self.build_seconds = 0.0
        if table is None:
            t0 = time.perf_counter()
            table = self.build_table()
            self.build_seconds = time.perf_counter() - t0
        table = np.asarray(table)
        if table.dtype != np.uint16 or table.shape != (self.num_free, theta_bins):
            raise ValueError(f"range table must be uint16 of shape {(self.num_free, theta_bins)}, "
                             f"got {table.dtype} {table.shape}")
        self.table = np.ascontiguousarray(table)
        ox, oy, yaw = occupancy_map.origin
        self._map_args = (float(ox), float(oy), math.cos(yaw), math.sin(yaw), occupancy_map.resolution, float(yaw))
        self._occupied = np.ascontiguousarray(occupancy_map.occupied)
        self._beams_cache = None

    # the exact (numpy) marcher: builds the table without numba, and is what ``refine`` approaches
    _cast_grid = ExactRayCaster._cast_grid

    @property
    def _consts(self) -> np.ndarray:
        """The query kernels' constants (indices ``C_*``)."""
        step = 2.0 * np.pi / self.theta_bins
        return np.array([1.0 / self.units_per_cell, self.max_cells, step, math.cos(step), math.sin(step),
                         self.refine])

    @property
    def _mode(self) -> int:
        return INTERPOLATIONS[self.interpolation]

    # ------------------------------------------------------------------ table
    @property
    def bin_angles(self) -> np.ndarray:
        """Grid-frame headings θ_k = 2πk/K of the table columns."""
        return 2.0 * np.pi * np.arange(self.theta_bins) / self.theta_bins

    @property
    def nbytes(self) -> int:
        return self.table.nbytes + self.index.nbytes

    def build_table(self) -> np.ndarray:
        """Exact ranges from every free cell centre along every bin heading, in fixed point."""
        rows, cols = np.nonzero(self.map.free)
        th = self.bin_angles
        table = np.empty((rows.size, self.theta_bins), dtype=np.uint16)
        if self.use_numba:
            from scipy.ndimage import distance_transform_cdt
            # chessboard distance: a lower bound of the Euclidean one, so the jumps stay safe
            clearance = np.minimum(distance_transform_cdt(~self.blocking, metric="chessboard"), 255).astype(np.uint8)
            rows, cols, cos_k, sin_k = rows.astype(np.int64), cols.astype(np.int64), np.cos(th), np.sin(th)
            jump = np.abs(np.abs(cos_k) - np.abs(sin_k)) > 1e-9  # not along an exact diagonal

            def build(part: slice) -> None:  # the kernel releases the GIL: one thread per core
                _build_kernel(self.blocking, clearance, rows[part], cols[part], cos_k, sin_k, jump, self.max_cells,
                              self.units_per_cell, table[part])

            workers = max(1, min(BUILD_THREADS, os.cpu_count() or 1))
            chunk = -(-rows.size // (4 * workers))  # a few chunks per thread: even finishing times
            parts = [slice(a, a + chunk) for a in range(0, rows.size, chunk)]
            if workers == 1:
                for part in parts:
                    build(part)
            else:
                from concurrent.futures import ThreadPoolExecutor
                with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="range_table") as pool:
                    list(pool.map(build, parts))
            return table
        chunk = max(1, 2_000_000 // self.theta_bins)
        for start in range(0, rows.size, chunk):
            r, c = rows[start:start + chunk], cols[start:start + chunk]
            ox = np.repeat(c + 1.5, th.size)
            oy = np.repeat(r + 1.5, th.size)
            cells = self._cast_grid(ox, oy, np.tile(np.cos(th), r.size), np.tile(np.sin(th), r.size))
            units = np.minimum(np.minimum(cells, self.max_cells) * self.units_per_cell + 0.5, TABLE_MAX_UNITS)
            table[start:start + r.size] = units.astype(np.uint16).reshape(r.size, th.size)
        return table

    @classmethod
    def for_map(cls, occupancy_map: OccupancyMap, max_range: float, theta_bins: int = DEFAULT_THETA_BINS,
                cache_dir=None, use_cache: bool = True, **kwargs) -> "LookupTableRayCaster":
        """The caster for a map, its table shared with a live caster of the same map and
        parameters, else loaded from the disk cache, else built and saved (atomically).
        ``cache_dir`` defaults to ``default_cache_dir()``; an unreadable or unwritable cache only
        costs a rebuild (with a warning). ``table_source`` says which: "memory", "disk" or
        "built". The compiled kernels are run once before returning, so JIT compilation is part
        of this call, not of the first scan."""
        theta_bins = int(theta_bins)
        name = cache_file_name(occupancy_map, max_range, theta_bins)
        path = (Path(cache_dir).expanduser() if cache_dir else default_cache_dir()) / name
        caster = None
        if use_cache:
            table, source = _LIVE_TABLES.get(name), "memory"
            if table is None:
                table, source = _load_table(path, occupancy_map, max_range, theta_bins), "disk"
            if table is not None:
                caster = cls(occupancy_map, max_range, theta_bins, table=table, **kwargs)
                caster.loaded_from_cache, caster.table_source = True, source
                caster.cache_path = path if source == "disk" else None
        if caster is None:
            caster = cls(occupancy_map, max_range, theta_bins, **kwargs)
            log.info("built the %d x %d range table in %.1f s", caster.num_free, theta_bins, caster.build_seconds)
            if use_cache:
                try:
                    _save_table(path, caster.table, _meta(occupancy_map, max_range, theta_bins))
                    caster.cache_path = path
                except OSError as exc:
                    log.warning("could not write the range table cache %s: %s", path, exc)
        if use_cache:
            _LIVE_TABLES[name] = caster.table
        caster.warm_up()
        return caster

    def warm_up(self) -> None:
        """Run the filter's compiled kernel once (JIT compile, or load from numba's cache);
        ``cast`` (simulator, tools) compiles on its first call."""
        if not self.use_numba:
            return
        pose = np.zeros((1, 3))
        angles = np.zeros(1)
        self.log_likelihood_sums(pose, angles, np.zeros((1, 2)), 1.0, 1.0, (0.0, 0.0, 0.0))

    # ------------------------------------------------------------------ queries
    def _beams(self, angles):
        """Per-beam (angle in bins in [0, K), cos, sin), cached for the last angle set."""
        angles = np.ascontiguousarray(np.asarray(angles, dtype=float).ravel())
        key = angles.tobytes()
        cached = self._beams_cache  # one attribute: safe if another thread replaces it meanwhile
        if cached is not None and cached[0] == key:
            return cached[1]
        if not np.all(np.isfinite(angles)):
            raise ValueError("beam angles must be finite")
        k = self.theta_bins
        beam_f = np.mod(angles * (k / (2.0 * np.pi)), k)
        beam_f[beam_f >= k] = 0.0
        arrays = (beam_f, np.cos(angles), np.sin(angles))
        self._beams_cache = (key, arrays)
        return arrays

    def cast(self, sensor_poses, angles) -> np.ndarray:
        """Expected ranges (metres), shape (N, B), for world sensor poses (N, 3) and beam angles (B,)."""
        if not self.use_numba:
            return self.cast_numpy(sensor_poses, angles)
        poses = np.ascontiguousarray(np.atleast_2d(np.asarray(sensor_poses, dtype=float)))
        beam_f, beam_c, beam_s = self._beams(angles)
        out = np.empty((poses.shape[0], beam_f.size))
        _cast_kernel(poses, *self._map_args, self.index, self.table, self.blocking, beam_f, beam_c, beam_s,
                     self._consts, self._mode, out)
        return out

    def cast_numpy(self, sensor_poses, angles) -> np.ndarray:
        """``cast`` in plain numpy: the reference for the compiled kernel, the fallback without numba.
        With ``refine`` the beams are cast by ``ExactRayCaster`` instead (what refining approaches)."""
        poses = np.atleast_2d(np.asarray(sensor_poses, dtype=float))
        angles = np.asarray(angles, dtype=float).ravel()
        k = self.theta_bins
        inv_units, max_cells, step, cos_step, sin_step = self._consts[:5]
        with np.errstate(invalid="ignore"):
            g = self.map.world_to_grid_pose(poses)
        finite = np.all(np.isfinite(g), axis=1)
        g[~finite] = 0.0  # a non-finite pose sees 0, as in the kernel
        col = np.floor(g[:, 0]).astype(np.int64)
        row = np.floor(g[:, 1]).astype(np.int64)
        inside = self.map.in_bounds(np.stack([col, row], axis=-1)) & finite
        cell = np.full(len(poses), -1, dtype=np.int64)
        cell[inside] = self.index[row[inside], col[inside]]
        ok = cell >= 0
        f0 = g[:, 2] * (k / (2.0 * np.pi))
        f0 -= k * np.floor(f0 / k)
        f0 = np.where(f0 >= k, f0 - k, f0)
        f = f0[:, None] + self._beams(angles)[0][None, :]
        f = np.where(f >= k, f - k, f)
        k0 = np.minimum(f.astype(np.int64), k - 1)
        k1 = np.where(k0 + 1 >= k, 0, k0 + 1)
        rows = np.where(ok, cell, 0)[:, None]
        q0 = self.table[rows, k0].astype(float)
        q1 = self.table[rows, k1].astype(float)
        ex, ey = g[:, 0] - (col + 0.5), g[:, 1] - (row + 0.5)
        c, s = np.cos(g[:, 2]), np.sin(g[:, 2])
        u, v = (c * ex + s * ey)[:, None], (c * ey - s * ex)[:, None]
        _, beam_c, beam_s = self._beams(angles)
        along, perp = u * beam_c + v * beam_s, v * beam_c - u * beam_s
        a = f - np.floor(f)
        nearest = np.where(a < 0.5, q0, q1) * inv_units - along
        if self.interpolation == "nearest":
            r = nearest
        elif self.interpolation == "linear":
            r = ((1.0 - a) * q0 + a * q1) * inv_units - along
        else:
            r0, r1 = q0 * inv_units, q1 * inv_units
            al = a * step
            al2 = al * al  # the kernel's Taylor series of sin/cos
            sa = al * (1.0 - al2 / 6.0 * (1.0 - al2 / 20.0))
            ca = 1.0 - al2 * 0.5 * (1.0 - al2 / 12.0 * (1.0 - al2 / 30.0))
            dxp, dyp = ca * along - sa * perp, ca * perp + sa * along
            e_x, e_y = r1 * cos_step - r0, r1 * sin_step
            den = ca * e_y - sa * e_x
            with np.errstate(divide="ignore", invalid="ignore"):
                line = ((r0 - dxp) * e_y + dyp * e_x) / den
            line = np.clip(line, np.minimum(r0, r1) - 1.0, np.maximum(r0, r1) + 1.0)
            fallback = (q0 >= TABLE_MAX_UNITS) | (q1 >= TABLE_MAX_UNITS) | ~(den > 1e-9)
            r = np.where(fallback, nearest, line)
        r = np.clip(r, 0.0, max_cells) * self.map.resolution
        if self.refine > 0 and ok.any():
            r[ok] = RayCaster.cast(self, poses[ok], angles)  # through _cast_grid: the exact marcher
        r[~ok] = 0.0
        return r

    def log_likelihood_sums(self, particles, angles, log_rows, cells_per_metre: float, squash_factor: float,
                            laser_offset=(0.0, 0.0, 0.0), out=None) -> np.ndarray:
        """The fused sensor-model sum used by ``SensorModel.log_likelihood``: for each particle
        (base pose, world frame), Σ_b log_rows[b, d_b] / squash_factor where d_b =
        rint(min(range_b · cells_per_metre, z_max)) indexes the range cast from the laser pose
        ``particle ⊕ laser_offset``; −inf for particles off the map or in an occupied cell.
        ``log_rows`` (B, z_max + 1) holds log p(z_b | d) for the measured z_b of each beam."""
        particles = np.ascontiguousarray(np.atleast_2d(np.asarray(particles, dtype=float)))
        log_rows = np.ascontiguousarray(log_rows, dtype=float)
        n = particles.shape[0]
        if out is None:
            out = np.empty(n)
        beam_f, beam_c, beam_s = self._beams(angles)
        ox, oy, oth = (float(v) for v in laser_offset)
        z_max = log_rows.shape[1] - 1
        if self.use_numba:
            _log_likelihood_kernel(particles, ox, oy, oth, *self._map_args, self._occupied, self.index, self.table,
                                   self.blocking,
                                   beam_f, beam_c, beam_s, self._consts, self._mode,
                                   float(cells_per_metre), float(z_max), log_rows, float(squash_factor), out)
            return out
        from .geometry import compose
        sensor = compose(particles, np.array([ox, oy, oth])) if (ox or oy or oth) else particles
        d = np.rint(np.clip(self.cast_numpy(sensor, angles) * cells_per_metre, 0, z_max)).astype(np.intp)
        out[:] = log_rows[np.arange(log_rows.shape[0])[None, :], d].sum(axis=1) / squash_factor
        out[self.map.is_occupied_or_outside(particles[:, :2])] = -np.inf
        return out


# ---------------------------------------------------------------------------------------------
# the disk cache
# ---------------------------------------------------------------------------------------------
def _meta(occupancy_map: OccupancyMap, max_range: float, theta_bins: int) -> dict:
    return {"format_version": FORMAT_VERSION, "map_digest": occupancy_map.digest, "max_range": float(max_range),
            "theta_bins": int(theta_bins), "num_free": int(np.count_nonzero(occupancy_map.free)),
            "units_per_cell": TABLE_MAX_UNITS / (float(max_range) / occupancy_map.resolution)}


def _load_table(path: Path, occupancy_map: OccupancyMap, max_range: float, theta_bins: int) -> np.ndarray | None:
    """The cached table, or None when missing, stale or unreadable."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            expected = _meta(occupancy_map, max_range, theta_bins)
            if meta != expected:
                log.warning("range table cache %s does not match this map/parameters: rebuilding", path)
                return None
            table = data["table"]
        if table.dtype != np.uint16 or table.shape != (expected["num_free"], theta_bins):
            raise ValueError(f"table has dtype {table.dtype} shape {table.shape}")
        return table
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        log.warning("unreadable range table cache %s (%s): rebuilding", path, exc)
        return None


def _save_table(path: Path, table: np.ndarray, meta: dict) -> None:
    """Write atomically: a temporary file in the same directory, then rename over ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, table=table, meta=np.array(json.dumps(meta, sort_keys=True)))
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
