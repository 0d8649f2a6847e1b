"""The range table of large maps, built tile by tile where the particles are.

``LookupTableRayCaster`` holds a row of ``K`` uint16 ranges for every free cell: 2·K bytes per
free cell (288 B at K = 144), so memory and build time grow with the map's free area (the Stata
basement tiled 3 × 3 has 2.8 M free cells of 20 M; figures in docs/performance.md), of which a car
ever sees a sliver. ``TiledLookupTableRayCaster`` keeps the very same table layout and query kernels,
but:

- the free cells are numbered tile by tile (square tiles of ``tile`` × ``tile`` cells, row-major
  inside a tile), so each tile's rows are one contiguous block ``table[start_t : start_t+1]``;
- the table is allocated zero-filled but not written: the operating system maps its pages only
  when they are first written (``np.zeros`` → calloc → anonymous mmap), so an unbuilt tile costs
  no memory;
- before every query (``prepare``), the tiles holding the sensor (laser) poses are looked up
  (t = ⌊row / tile⌋ · n_cols + ⌊col / tile⌋ of the laser's cell) and the missing ones built by the
  same compiled marcher (``kernels.build_kernel``), so every row a query reads is exactly the row
  the full table would hold.

Resident memory is then O(map cells) for the grids (int32 index, the blocking and clearance
grids: ~6 bytes per cell) plus 2·K bytes per free cell *of the tiles visited*. The query itself
is the full table's (same kernel, same numbers), so accuracy is the full table's by
construction; ``test_large_map.py`` asserts the rows equal a full build's and the casts the
exact caster's. A global spread over the whole map visits every tile (the full table's build
time and memory, spread over the first scan).
"""
from __future__ import annotations

import mmap
import os
import threading
import time
from contextlib import contextmanager

import numpy as np

from localization.core.occupancy_map import OccupancyMap
from localization.core.raycast.exact import RayCaster
from localization.core.raycast.kernels import HAVE_NUMBA, TABLE_MAX_UNITS
from localization.core.raycast.lookup_table import (  # noqa: F401 - chessboard_*: re-exported
    BUILD_THREADS,
    DEFAULT_THETA_BINS,
    LookupTableRayCaster,
    chessboard_clearance,
    chessboard_clearance_numpy,
)

DEFAULT_TILE_CELLS = 32  # cells per tile side (1.6 m at 0.05 m/cell)

class TiledLookupTableRayCaster(LookupTableRayCaster):
    """``LookupTableRayCaster`` whose table rows are built per tile on first use (module docstring)."""

    def __init__(self, occupancy_map: OccupancyMap, max_range: float, theta_bins: int = DEFAULT_THETA_BINS,
                 interpolation: str = "line", refine: float = 0.0, tile: int = DEFAULT_TILE_CELLS,
                 use_numba: bool = HAVE_NUMBA):
        RayCaster.__init__(self, occupancy_map, max_range)
        t0 = time.perf_counter()
        self._set_query_options(theta_bins, interpolation, refine, use_numba)
        theta_bins = self.theta_bins
        self.tile = int(tile)
        free = occupancy_map.free
        h, w = free.shape
        self.tiles_shape = (-(-h // self.tile), -(-w // self.tile))
        n_tiles = self.tiles_shape[0] * self.tiles_shape[1]
        # free cells numbered tile by tile (tile id, then row-major in the tile), one band of tile
        # rows at a time so the temporaries stay small on a 20 M-cell map
        self.index = np.full(free.shape, -1, dtype=np.int32)
        counts = np.zeros(n_tiles, dtype=np.int64)
        next_row = 0
        for band in range(self.tiles_shape[0]):
            r0 = band * self.tile
            rows, cols = np.nonzero(free[r0:r0 + self.tile])
            tile_id = band * self.tiles_shape[1] + cols // self.tile
            order = np.argsort(tile_id, kind="stable")  # nonzero is row-major: stable keeps it in a tile
            self.index[rows[order] + r0, cols[order]] = np.arange(next_row, next_row + rows.size, dtype=np.int32)
            counts += np.bincount(tile_id, minlength=n_tiles)
            next_row += rows.size
        self.num_free = int(next_row)
        self.tile_start = np.zeros(n_tiles + 1, dtype=np.int64)
        np.cumsum(counts, out=self.tile_start[1:])
        self.built = counts == 0  # a tile without free cells has nothing to build
        self.units_per_cell = TABLE_MAX_UNITS / self.max_cells
        # an anonymous mapping: zero-filled, its pages mapped when first written, and given back to
        # the system by ``release_tiles`` (madvise DONTNEED: read as zeros again, rebuilt on demand)
        self._table_buffer = mmap.mmap(-1, max(1, self.num_free * theta_bins * 2))
        self.table = np.frombuffer(self._table_buffer, dtype=np.uint16,
                                   count=self.num_free * theta_bins).reshape(self.num_free, theta_bins)
        self._build_consts = self._make_build_consts() if self.use_numba else None  # kept: tiles come later
        self._build_lock = threading.Lock()
        self.loaded_from_cache, self.table_source, self.cache_path = False, "tiles", None
        self.build_seconds = 0.0  # seconds spent building tiles so far
        self.setup_seconds = time.perf_counter() - t0

    @classmethod
    def for_map(cls, occupancy_map: OccupancyMap, max_range: float, theta_bins: int = DEFAULT_THETA_BINS,
                cache_dir=None, use_cache: bool = True, **kwargs) -> "TiledLookupTableRayCaster":
        """As ``LookupTableRayCaster.for_map``; nothing is cached on disk (nothing is built up front)."""
        caster = cls(occupancy_map, max_range, theta_bins, **kwargs)
        caster.warm_up()
        return caster

    # ------------------------------------------------------------------ tiles
    @property
    def tiles_built(self) -> int:
        return int(np.count_nonzero(self.built[self.tile_start[1:] > self.tile_start[:-1]]))

    @property
    def rows_built(self) -> int:
        sizes = np.diff(self.tile_start)
        return int(sizes[self.built].sum())

    @property
    def nbytes(self) -> int:
        """Bytes actually holding ranges (built rows) plus the index."""
        return self.rows_built * self.theta_bins * 2 + self.index.nbytes

    def tiles_of(self, sensor_poses) -> np.ndarray:
        """Ids of the tiles holding world sensor poses (N, 3) (off-map poses: none), unique."""
        ids = self.tile_ids(np.asarray(sensor_poses, dtype=float).reshape(-1, 3)[:, :2])
        return np.unique(ids[ids >= 0])

    def tile_ids(self, xy) -> np.ndarray:
        """Tile id of each world point (N, 2) (-1 off the map). Same arithmetic as ``kernels.locate``."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        ox, oy, c, s, res, _ = self._map_args
        dx, dy = xy[:, 0] - ox, xy[:, 1] - oy
        gx = (c * dx + s * dy) / res
        gy = (-s * dx + c * dy) / res
        h, w = self.index.shape
        out = np.full(len(xy), -1, dtype=np.int64)
        ok = (gx >= 0.0) & (gx < w) & (gy >= 0.0) & (gy < h)
        out[ok] = (np.floor(gy[ok]).astype(np.int64) // self.tile) * self.tiles_shape[1] + \
            np.floor(gx[ok]).astype(np.int64) // self.tile
        return out

    def release_tiles(self, tiles) -> int:
        """Give the memory of built tiles back (the whole pages inside each tile's rows) and mark them
        unbuilt: the next query there builds them again. For passes that touch the whole map once
        (scoring a global lattice) without keeping it. Returns how many tiles were released."""
        tiles = np.asarray(tiles, dtype=np.int64).ravel()
        if tiles.size == 0 or not hasattr(self._table_buffer, "madvise"):
            return 0
        page, row_bytes = mmap.PAGESIZE, self.theta_bins * 2
        released = 0
        with self._build_lock:
            for t in tiles[self.built[tiles] & (self.tile_start[tiles + 1] > self.tile_start[tiles])].tolist():
                a = -(-int(self.tile_start[t]) * row_bytes // page) * page  # whole pages inside the tile
                b = int(self.tile_start[t + 1]) * row_bytes // page * page
                if b > a:
                    self._table_buffer.madvise(mmap.MADV_DONTNEED, a, b - a)
                self.built[t] = False
                released += 1
        return released

    @contextmanager
    def scratch(self):
        """A scope whose tiles are temporary: the tiles built inside it (not those built before)
        are released when it ends, e.g. scoring a global lattice one chunk at a time."""
        kept = self.built.copy()
        try:
            yield self
        finally:
            self.release_tiles(np.flatnonzero(self.built & ~kept))

    def locality_order(self, xy) -> np.ndarray:
        """A permutation of world positions (K, 2) by tile (stable: their order within a tile kept)."""
        return np.argsort(self.tile_ids(xy), kind="stable")

    def ensure_tiles(self, tiles) -> int:
        """Build the listed tiles not built yet; returns how many were built."""
        tiles = np.asarray(tiles, dtype=np.int64).ravel()
        missing = tiles[~self.built[tiles]]
        if missing.size == 0:
            return 0
        with self._build_lock:
            missing = missing[~self.built[missing]]
            t0 = time.perf_counter()
            workers = max(1, min(BUILD_THREADS, os.cpu_count() or 1))
            if self.use_numba and workers > 1 and missing.size >= 4 * workers:  # the kernel releases the GIL
                from concurrent.futures import ThreadPoolExecutor
                with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="range_tiles") as pool:
                    list(pool.map(self._build_tile, missing.tolist()))
            else:
                for t in missing:
                    self._build_tile(int(t))
            self.build_seconds += time.perf_counter() - t0
        return int(missing.size)

    def _build_tile(self, t: int) -> None:
        tr, tc = divmod(t, self.tiles_shape[1])
        r0, c0 = tr * self.tile, tc * self.tile
        rows, cols = np.nonzero(self.map.free[r0:r0 + self.tile, c0:c0 + self.tile])
        rows, cols = rows + r0, cols + c0
        self._build_rows(rows, cols, self.table[self.tile_start[t]:self.tile_start[t + 1]])
        self.built[t] = True

    def build_table(self) -> np.ndarray:
        """Build every tile (what the full table holds); returns the table."""
        self.ensure_tiles(np.arange(self.built.size))
        return self.table

    def prepare(self, particles, laser_offset=(0.0, 0.0, 0.0)) -> None:
        """Build the tiles the lasers of base poses ``particles`` (N, 3) sit in (as the fused
        sensor kernel places them: laser = particle ∘ offset)."""
        p = np.asarray(particles, dtype=float).reshape(-1, 3)
        ox, oy, oth = (float(v) for v in laser_offset)
        if ox or oy:
            c, s = np.cos(p[:, 2]), np.sin(p[:, 2])
            p = np.column_stack([p[:, 0] + c * ox - s * oy, p[:, 1] + s * ox + c * oy, p[:, 2] + oth])
        self.ensure_tiles(self.tiles_of(p))

    # ------------------------------------------------------------------ queries
    def cast(self, sensor_poses, angles, *args, **kwargs) -> np.ndarray:
        self.prepare(sensor_poses)
        return super().cast(sensor_poses, angles, *args, **kwargs)

    def cast_numpy(self, sensor_poses, angles, *args, **kwargs) -> np.ndarray:
        self.prepare(sensor_poses)
        return super().cast_numpy(sensor_poses, angles, *args, **kwargs)
