"""Lookup-table ray casting: expected ranges precomputed over (free cell, heading bin).

Real time at thousands of particles needs a ray cast whose cost is a memory read, not a march
through the grid. ``LookupTableRayCaster`` precomputes, for every *free* cell of the map (a
sensor in any other cell sees 0, see ``exact.py``) and each of ``theta_bins`` headings
θ_k = 2πk / K in the grid frame, the exact (Amanatides–Woo) range from the cell centre:

- ``index``: int32 (H, W) grid, the table row of each free cell, -1 elsewhere;
- ``table``: uint16 (F, K), ranges in fixed point, ``units_per_cell`` = 65535 / max_cells units
  per cell. One row holds every heading of one cell, so the beams of one particle read a few
  consecutive cache lines.

A query at a continuous sensor pose (x, y, θ) reads the two bins k0, k1 around each beam from the
row of the sensor's cell and intersects the beam — cast from the sensor's true position in the
cell, not the centre — with the line through the two bins' hit points:

    r = ((r0 − d'x)·e_y + d'y·e_x) / (cos α·e_y − sin α·e_x),   e = r1·(cos Δ, sin Δ) − (r0, 0)

(Δ the bin step, α the beam's angle past bin k0, d' the sensor's offset from the cell centre in
bin k0's frame), clipped to [min(r0, r1) − 1, max(r0, r1) + 1] cells: exact for a straight wall
at any incidence and continuous in the pose elsewhere; where a bin sees nothing within max range
the nearest bin is used. The *exact finish* (``refine`` > 0, ray caster ``lookup_table_exact``)
then marches each beam through the grid from ``refine`` cells short of the nearest of its estimate
and its two bins' ranges, so wall edges between bins come out as with ``ExactRayCaster``.

The table is built by the compiled marcher of ``kernels.py`` (sphere tracing far from walls, the
exact march near them; on all cores) and cached on disk by ``table_cache.py``. Accuracy against
``ExactRayCaster``, speed and memory: docs/performance.md.
"""
from __future__ import annotations

import logging
import math
import os
import time
from pathlib import Path

import numpy as np

from localization.core.occupancy_map import OccupancyMap
from localization.core.paths import cache_dir as default_cache_dir
from localization.core.raycast import kernels as K
from localization.core.raycast.exact import ExactRayCaster, RayCaster
from localization.core.raycast.kernels import HAVE_NUMBA, TABLE_MAX_UNITS
from localization.core.raycast.table_cache import LIVE_TABLES, cache_file_name, load_table, save_table, table_meta

DEFAULT_THETA_BINS = 144
BUILD_THREADS = 4  # at most: the table is built once per map, with every core the machine has
BUILD_SECONDS_PER_RAY = 2.5e-7  # s per (free cell x heading) ray of a table build on one core: build_estimate

log = logging.getLogger(__name__)

INTERPOLATIONS = {"nearest": 0, "linear": 1, "line": 2}


def chessboard_clearance(blocking) -> np.ndarray:
    """uint8 min(255, chessboard distance in cells to the nearest blocking cell): the build's
    clearance (``kernels.build_kernel``) in one byte per cell, no int32 temporaries."""
    blocking = np.ascontiguousarray(blocking, dtype=bool)
    if not HAVE_NUMBA:  # pragma: no cover
        return chessboard_clearance_numpy(blocking)
    out = np.empty(blocking.shape, dtype=np.uint8)
    K.chessboard_kernel(blocking, out)
    return out


def chessboard_clearance_numpy(blocking) -> np.ndarray:
    """The reference of ``chessboard_clearance`` (scipy; int32 temporaries)."""
    from scipy.ndimage import distance_transform_cdt
    return np.minimum(distance_transform_cdt(~np.asarray(blocking, dtype=bool), metric="chessboard"),
                      255).astype(np.uint8)


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

    _build_consts = None  # the compiled build's inputs while rows are being built (_make_build_consts)

    def __init__(self, occupancy_map: OccupancyMap, max_range: float, theta_bins: int = DEFAULT_THETA_BINS,
                 table: np.ndarray | None = None, interpolation: str = "line", refine: float = 0.0,
                 use_numba: bool = HAVE_NUMBA):
        super().__init__(occupancy_map, max_range)
        self._set_query_options(theta_bins, interpolation, refine, use_numba)
        theta_bins = self.theta_bins
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

    def _set_query_options(self, theta_bins, interpolation: str, refine: float, use_numba: bool) -> None:
        """Check and keep the query options and the map's constants for the kernels (shared with
        ``TiledLookupTableRayCaster``)."""
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
        ox, oy, yaw = self.map.origin
        self._map_args = (float(ox), float(oy), math.cos(yaw), math.sin(yaw), self.map.resolution, float(yaw))
        self._occupied = np.ascontiguousarray(self.map.occupied)
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
        table = np.empty((rows.size, self.theta_bins), dtype=np.uint16)
        if self.use_numba:
            self._build_consts = self._make_build_consts()  # once, before the threads share it
            workers = max(1, min(BUILD_THREADS, os.cpu_count() or 1))
            chunk = -(-rows.size // (4 * workers))  # a few chunks per thread: even finishing times
        else:
            workers, chunk = 1, max(1, 2_000_000 // self.theta_bins)  # bounded numpy temporaries
        parts = [slice(a, a + chunk) for a in range(0, rows.size, chunk)]

        def build(part: slice) -> None:  # the kernel releases the GIL: one thread per core
            self._build_rows(rows[part], cols[part], table[part])

        if workers == 1:
            for part in parts:
                build(part)
        else:
            from concurrent.futures import ThreadPoolExecutor
            with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="range_table") as pool:
                list(pool.map(build, parts))
        self._build_consts = None  # the full table is built: its clearance grid is not needed again
        return table

    def _make_build_consts(self) -> tuple:
        """The compiled build's inputs: the clearance grid (chessboard distance, a lower bound of the
        Euclidean one, so the marcher's jumps stay safe) and the bin headings (cos, sin, and which
        ones are not an exact diagonal)."""
        th = self.bin_angles
        cos_k, sin_k = np.cos(th), np.sin(th)
        return chessboard_clearance(self.blocking), cos_k, sin_k, np.abs(np.abs(cos_k) - np.abs(sin_k)) > 1e-9

    def _build_rows(self, rows, cols, out) -> None:
        """The table rows of free cells (``rows``, ``cols``) into ``out`` (the compiled marcher, or
        the numpy caster); shared by the full build and the tiled table's tiles."""
        if self.use_numba:
            clearance, cos_k, sin_k, jump = self._build_consts
            K.build_kernel(self.blocking, clearance, np.asarray(rows, dtype=np.int64), np.asarray(cols, dtype=np.int64),
                           cos_k, sin_k, jump, self.max_cells, self.units_per_cell, out)
            return
        th = self.bin_angles
        cells = self._cast_grid(np.repeat(cols + 1.5, th.size), np.repeat(rows + 1.5, th.size),
                                np.tile(np.cos(th), rows.size), np.tile(np.sin(th), rows.size))
        units = np.minimum(np.minimum(cells, self.max_cells) * self.units_per_cell + 0.5, TABLE_MAX_UNITS)
        out[:] = units.astype(np.uint16).reshape(rows.size, th.size)

    @staticmethod
    def cached_source(occupancy_map: OccupancyMap, max_range: float, theta_bins: int = DEFAULT_THETA_BINS,
                      cache_dir=None) -> str:
        """Where ``for_map`` would find this table: "memory" (a live caster's), "disk" (the cache
        file exists; a stale one is still rebuilt) or "" (it would be built)."""
        name = cache_file_name(occupancy_map, max_range, int(theta_bins))
        if LIVE_TABLES.get(name) is not None:
            return "memory"
        path = (Path(cache_dir).expanduser() if cache_dir else default_cache_dir()) / name
        return "disk" if path.is_file() else ""

    @staticmethod
    def build_estimate(occupancy_map: OccupancyMap, theta_bins: int = DEFAULT_THETA_BINS) -> float:
        """Expected seconds of a full table build on this machine (``BUILD_SECONDS_PER_RAY`` per ray,
        on up to BUILD_THREADS cores, at most two counted: the machine is rarely idle)."""
        rays = int(np.count_nonzero(occupancy_map.free)) * int(theta_bins)
        return rays * BUILD_SECONDS_PER_RAY / max(1, min(2, BUILD_THREADS, os.cpu_count() or 1))

    @classmethod
    def for_map(cls, occupancy_map: OccupancyMap, max_range: float, theta_bins: int = DEFAULT_THETA_BINS,
                cache_dir=None, use_cache: bool = True, **kwargs) -> "LookupTableRayCaster":
        """The caster for a map, its table shared with a live caster of the same map and
        parameters, else loaded from the disk cache, else built and saved (atomically).
        ``cache_dir`` defaults to ``paths.cache_dir()``; an unreadable or unwritable cache only
        costs a rebuild (with a warning). ``table_source`` says which: "memory", "disk" or
        "built". The compiled kernels are run once before returning, so JIT compilation is part
        of this call, not of the first scan."""
        theta_bins = int(theta_bins)
        name = cache_file_name(occupancy_map, max_range, theta_bins)
        path = (Path(cache_dir).expanduser() if cache_dir else default_cache_dir()) / name
        caster = None
        if use_cache:
            table, source = LIVE_TABLES.get(name), "memory"
            if table is None:
                table, source = load_table(path, occupancy_map, max_range, theta_bins), "disk"
            if table is not None:
                caster = cls(occupancy_map, max_range, theta_bins, table=table, **kwargs)
                caster.loaded_from_cache, caster.table_source = True, source
                caster.cache_path = path if source == "disk" else None
        if caster is None:
            caster = cls(occupancy_map, max_range, theta_bins, **kwargs)
            log.info("built the %d x %d range table in %.1f s", caster.num_free, theta_bins, caster.build_seconds)
            if use_cache:
                try:
                    save_table(path, caster.table, table_meta(occupancy_map, max_range, theta_bins))
                    caster.cache_path = path
                except OSError as exc:
                    log.warning("could not write the range table cache %s: %s", path, exc)
        if use_cache:
            LIVE_TABLES[name] = caster.table
        caster.warm_up()
        return caster

    def warm_up(self) -> None:
        """Run the compiled cast kernel once (JIT compile, or load from numba's cache), so it is
        part of the set-up, not of the first scan. Sensor models warm their own fused kernels."""
        if self.use_numba:
            self.cast(np.zeros((1, 3)), np.zeros(1))

    def prepare(self, particles, laser_offset=(0.0, 0.0, 0.0)) -> None:
        """Called with the base poses before a fused query: nothing to do for a full table
        (``TiledLookupTableRayCaster`` builds the tiles the lasers are in)."""

    def kernel_args(self, angles) -> tuple:
        """What a fused compiled kernel needs to cast beams ``angles`` from any sensor pose
        (``kernels.locate`` + ``kernels.beam_ranges`` + ``kernels.refine``): map pose, occupied
        grid, index, table, blocking grid, the beams in bins, constants, interpolation mode."""
        beam_f, beam_c, beam_s = self._beams(angles)
        return (*self._map_args, self._occupied, self.index, self.table, self.blocking, beam_f, beam_c, beam_s,
                self._consts, self._mode)

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
        K.cast_kernel(poses, *self._map_args, self.index, self.table, self.blocking, beam_f, beam_c, beam_s,
                     self._consts, self._mode, out)
        return out

    def cast_numpy(self, sensor_poses, angles, offsets=None) -> np.ndarray:
        """``cast`` in plain numpy (``table_cast_numpy``): the compiled kernel's reference."""
        return table_cast_numpy(self, sensor_poses, angles, offsets)


def table_cast_numpy(self: "LookupTableRayCaster", sensor_poses, angles, offsets=None) -> np.ndarray:
    """``cast`` in plain numpy: the reference for the compiled kernel, the fallback without numba.
    With ``refine`` the beams are cast by ``ExactRayCaster`` instead (what refining approaches).
    ``offsets`` (B, 2): each beam's origin moved by (dx, dy) metres in the sensor frame (a
    deskewed sweep), folded into the offset from the cell centre as the fused beam kernel does."""
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
    if offsets is not None:
        offsets = np.asarray(offsets, dtype=float).reshape(-1, 2) / self.map.resolution
        u, v = u + offsets[None, :, 0], v + offsets[None, :, 1]
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
    if self.refine > 0 and ok.any() and offsets is None:
        r[ok] = RayCaster.cast(self, poses[ok], angles)  # through _cast_grid: the exact marcher
    elif self.refine > 0 and ok.any():  # each beam from its own origin
        gc, gs = np.cos(poses[ok, 2])[:, None], np.sin(poses[ok, 2])[:, None]
        dx, dy = offsets[None, :, 0] * self.map.resolution, offsets[None, :, 1] * self.map.resolution
        origins = np.stack([poses[ok, 0:1] + gc * dx - gs * dy, poses[ok, 1:2] + gs * dx + gc * dy,
                            np.broadcast_to(poses[ok, 2:3], (int(ok.sum()), angles.size))], axis=-1)
        r[ok] = self.cast_rays(origins.reshape(-1, 3), np.tile(angles, int(ok.sum()))).reshape(-1, angles.size)
    r[~ok] = 0.0
    return r
