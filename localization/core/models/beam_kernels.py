"""The beam model's compiled pass (``BeamModel.log_likelihood`` with the lookup-table caster): per particle
the laser pose, each beam's interpolated range from the table (``raycast.kernels``), its table column
and the sum of the log table rows, with no (N, B) temporaries. ``BeamModel.log_likelihood_numpy`` is its
numpy reference, asserted equal in the tests.
"""
from __future__ import annotations

import math
import os

import numpy as np

from localization.core.raycast import kernels as K
from localization.core.raycast.kernels import HAVE_NUMBA


def choose_threading_layer(layer: str = "workqueue") -> str:
    """numba's threading layer for ``fused_kernel_parallel``, unless NUMBA_THREADING_LAYER names one; numba
    fixes it when its pool first starts, so a later call changes nothing. ``"workqueue"`` (chosen at import):
    its threads wait on a condition variable and start at once after an idle, as the live node's between
    scans; OpenMP's threads (``"omp"``) spin, then sleep, and a pass after such an idle took milliseconds
    longer on two threads than on one. ``"omp"`` suits passes run back to back (a replay), where its
    spinning threads start sooner; it is also safe to call from several threads at once, the work
    queue is not (docs/performance.md)."""
    if not HAVE_NUMBA:
        return "none"
    from numba.core import config
    if not os.environ.get("NUMBA_THREADING_LAYER"):
        config.THREADING_LAYER = layer
    return str(config.THREADING_LAYER)


if HAVE_NUMBA:
    from numba import njit, prange

    from localization.core.raycast.kernels import (
        beam_ranges,
        bin_above,
        bin_below,
        bin_range,
        locate,
        refine,
        wall_line_range,
    )

    choose_threading_layer()


if HAVE_NUMBA:
    @njit(cache=True, nogil=True)
    def fused_rows(lo, hi, particles, off_x, off_y, off_th, map_ox, map_oy, map_c, map_s, resolution, map_yaw,
                    occupied, index, table, blocking, beam_f, beam_c, beam_s, consts, mode, beam_du, beam_dv,
                    bins_per_metre, z_max, log_rows, squash_factor, out, cols_out):  # pragma: no cover - compiled
        """For particles lo … hi − 1: out[i] = Σ_b log p(z_b | d_b(particle i)) / squash_factor; −inf for
        particles off the map or in an occupied cell. ``log_rows[b]`` is the log table row of the measured z_b (columns
        0 … z_max); (beam_du[b], beam_dv[b]): beam b's origin offset from the laser, laser frame, map
        cells; ``bins_per_metre``: 1 / table_resolution. ``cols_out`` (N, B), unless it has no rows:
        also each particle's table column d_b (rows of impossible particles are left unwritten).

        The sums are taken four particles at a time: each particle's columns wait in ``cols`` until four are
        ready, then one pass over the beams adds the four sums side by side. Each sum is still added beam by
        beam from b = 0 (the same value bit for bit as one particle alone); four independent chains of additions
        overlap where one chain waits on each addition (docs/performance.md)."""
        write = cols_out.shape[0] > 0
        n_bins = table.shape[1]
        h, w = occupied.shape
        n_beams = beam_f.size
        fs = np.empty(n_beams)
        q0s = np.empty(n_beams)
        q1s = np.empty(n_beams)
        cells = np.empty(n_beams)
        ks = np.empty(n_beams, dtype=np.uint64)
        cols = np.empty((4, n_beams), dtype=np.int64)  # the columns of the particles waiting for their sums ...
        waiting = np.empty(4, dtype=np.int64)  # ... and those particles
        count = 0
        inv_units, max_cells = consts[K.C_INV_UNITS], consts[K.C_MAX_CELLS]
        step, cos_step, sin_step = consts[K.C_STEP], consts[K.C_COS_STEP], consts[K.C_SIN_STEP]
        blind = 0.0  # a laser outside free space sees 0 on every beam
        for b in range(n_beams):
            blind += log_rows[b, 0]
        for i in range(lo, hi):
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
            cell, f0, u, v, sx, sy, sc, ss = locate(px + c * off_x - s * off_y, py + s * off_x + c * off_y,
                                                    pth + off_th, map_ox, map_oy, map_c, map_s, resolution,
                                                    map_yaw, index, n_bins)
            if cell < 0:
                out[i] = blind / squash_factor
                if write:
                    for b in range(n_beams):
                        cols_out[i, b] = 0
                continue
            # raycast.kernels.beam_ranges' three passes, here in the body that owns the scratch arrays: as a
            # called function they compile to slower code (docs/performance.md)
            row = table[cell]
            for b in range(n_beams):
                f = f0 + beam_f[b]
                fs[b] = f - n_bins if f >= n_bins else f
            for b in range(n_beams):  # each beam's bin apart from the reads: this pass compiles to SIMD
                ks[b] = bin_below(fs[b], n_bins)
            for b in range(n_beams):
                k0 = ks[b]
                q0s[b] = row[k0]
                q1s[b] = row[bin_above(k0, n_bins)]
            if mode == 2:
                for b in range(n_beams):
                    cells[b] = wall_line_range(fs[b], q0s[b], q1s[b], u + beam_du[b], v + beam_dv[b], beam_c[b],
                                               beam_s[b], inv_units, step, cos_step, sin_step, max_cells)
            else:
                for b in range(n_beams):
                    cells[b] = bin_range(mode, fs[b], q0s[b], q1s[b], u + beam_du[b], v + beam_dv[b], beam_c[b],
                                         beam_s[b], inv_units, max_cells)
            if consts[K.C_REFINE] > 0.0:
                refine(blocking, sx + 1.0, sy + 1.0, sc, ss, beam_du, beam_dv, beam_c, beam_s, consts, q0s, q1s,
                       cells)
            col = cols[count]
            for b in range(n_beams):  # the table columns apart from the sum: this pass compiles to SIMD
                d = (cells[b] * resolution) * bins_per_metre  # map metres, then table cells as BeamModel.to_cells
                d = z_max if d > z_max else d
                col[b] = int(np.rint(d))
            if write:
                for b in range(n_beams):
                    cols_out[i, b] = col[b]
            waiting[count] = i
            count += 1
            if count < 4:
                continue
            t0 = t1 = t2 = t3 = 0.0
            for b in range(n_beams):  # cols >= 0: an unsigned index
                t0 += log_rows[b, np.uint64(cols[0, b])]
                t1 += log_rows[b, np.uint64(cols[1, b])]
                t2 += log_rows[b, np.uint64(cols[2, b])]
                t3 += log_rows[b, np.uint64(cols[3, b])]
            out[waiting[0]] = t0 / squash_factor
            out[waiting[1]] = t1 / squash_factor
            out[waiting[2]] = t2 / squash_factor
            out[waiting[3]] = t3 / squash_factor
            count = 0
        for j in range(count):  # the last particles, fewer than four
            total = 0.0
            for b in range(n_beams):
                total += log_rows[b, np.uint64(cols[j, b])]
            out[waiting[j]] = total / squash_factor

    @njit(cache=True, nogil=True)
    def fused_kernel(particles, off_x, off_y, off_th, map_ox, map_oy, map_c, map_s, resolution, map_yaw, occupied,
                      index, table, blocking, beam_f, beam_c, beam_s, consts, mode, beam_du, beam_dv, bins_per_metre,
                      z_max, log_rows, squash_factor, out, cols_out):  # pragma: no cover - compiled
        """The fused pass over every particle (``fused_rows``), on this thread."""
        fused_rows(0, particles.shape[0], particles, off_x, off_y, off_th, map_ox, map_oy, map_c, map_s, resolution,
                    map_yaw, occupied, index, table, blocking, beam_f, beam_c, beam_s, consts, mode, beam_du, beam_dv,
                    bins_per_metre, z_max, log_rows, squash_factor, out, cols_out)

    @njit(cache=True, nogil=True, parallel=True)
    def fused_kernel_parallel(n_blocks, particles, off_x, off_y, off_th, map_ox, map_oy, map_c, map_s, resolution,
                               map_yaw, occupied, index, table, blocking, beam_f, beam_c, beam_s, consts, mode,
                               beam_du, beam_dv, bins_per_metre, z_max, log_rows, squash_factor, out,
                               cols_out):  # pragma: no cover - compiled
        """The same pass with the particles cut into ``n_blocks`` contiguous blocks run on numba's threads:
        each particle's sum is computed exactly as on one thread (the same weights, bit for bit)."""
        n = particles.shape[0]
        for blk in prange(n_blocks):
            fused_rows(blk * n // n_blocks, (blk + 1) * n // n_blocks, particles, off_x, off_y, off_th, map_ox,
                        map_oy, map_c, map_s, resolution, map_yaw, occupied, index, table, blocking, beam_f, beam_c,
                        beam_s, consts, mode, beam_du, beam_dv, bins_per_metre, z_max, log_rows, squash_factor, out,
                        cols_out)

    @njit(cache=True, nogil=True)
    def cast_rows(poses, off_x, off_y, off_th, map_ox, map_oy, map_c, map_s, resolution, map_yaw, occupied, index,
                  table, blocking, beam_f, beam_c, beam_s, consts, mode, beam_du, beam_dv, fs, q0s, q1s, cells,
                  out):  # pragma: no cover - compiled
        """out[i, b]: the range (map metres) of beam b cast from the laser of base pose i exactly as ``fused_rows``
        casts it (``BeamModel.expected_ranges`` is its numpy reference); a laser outside free space sees 0.
        ``fs``, ``q0s``, ``q1s``, ``cells``: (B,) scratch."""
        n_bins = table.shape[1]
        n_beams = beam_f.size
        for i in range(poses.shape[0]):
            px = poses[i, 0]
            py = poses[i, 1]
            pth = poses[i, 2]
            c = math.cos(pth)
            s = math.sin(pth)
            cell, f0, u, v, sx, sy, sc, ss = locate(px + c * off_x - s * off_y, py + s * off_x + c * off_y,
                                                    pth + off_th, map_ox, map_oy, map_c, map_s, resolution,
                                                    map_yaw, index, n_bins)
            if cell < 0:
                for b in range(n_beams):
                    out[i, b] = 0.0
                continue
            beam_ranges(table[cell], f0, u, v, beam_du, beam_dv, beam_f, beam_c, beam_s, consts, mode, fs, q0s,
                        q1s, cells)
            if consts[K.C_REFINE] > 0.0:
                refine(blocking, sx + 1.0, sy + 1.0, sc, ss, beam_du, beam_dv, beam_c, beam_s, consts, q0s, q1s,
                       cells)
            for b in range(n_beams):
                out[i, b] = cells[b] * resolution

    @njit(cache=True, nogil=True)
    def skip_votes(cols, z, threshold, out, votes):  # pragma: no cover - compiled
        """Beam skipping's counts: votes[b] = the particles that can see (``out`` finite) whose table column of
        beam b lies within ``threshold`` cells of the measured row z[b] (``BeamModel._skipped_sum_numpy``)."""
        votes[:] = 0
        for i in range(cols.shape[0]):
            if not math.isfinite(out[i]):
                continue
            for b in range(cols.shape[1]):
                if abs(cols[i, b] - z[b]) <= threshold:
                    votes[b] += 1

    @njit(cache=True, nogil=True)
    def masked_sum(log_rows, cols, used, squash_factor, out):  # pragma: no cover - compiled
        """out[i] = Σ over the ``used`` beams of log_rows[b, cols[i, b]] / squash_factor for the particles that
        can see (``out`` finite); the others stay −inf."""
        for i in range(cols.shape[0]):
            if not math.isfinite(out[i]):
                continue
            total = 0.0
            for b in range(cols.shape[1]):
                if used[b]:
                    total += log_rows[b, cols[i, b]]
            out[i] = total / squash_factor

    # it inlines locate, the per-beam rules, beam_ranges and refine: their file's changes must reach its
    # cached compilation too
    from localization.core.compile_cache import drop_if_older
    for _kernel in (fused_rows, fused_kernel, fused_kernel_parallel, cast_rows):
        drop_if_older(_kernel, K.__file__)
else:  # pragma: no cover
    fused_kernel = fused_kernel_parallel = cast_rows = skip_votes = masked_sum = None


def probe_cast(caster, laser, resolution: float, angles, offsets=None):
    """``poses (k, 3) -> (k, B)``: the beams at ``angles`` (rad; ``offsets`` (B, 3) a deskewed sweep's) cast from
    the laser (``laser`` = its pose in the robot frame) of each base pose by ``cast_rows``, with ``caster`` (a
    lookup-table caster; ``resolution``: the map's cell, m)."""
    angles = np.asarray(angles, dtype=float).ravel()
    if offsets is None:
        du = dv = np.zeros(angles.size)
    else:
        angles = angles + offsets[:, 2]
        du = np.ascontiguousarray(offsets[:, 0] / resolution)  # cells, laser frame
        dv = np.ascontiguousarray(offsets[:, 1] / resolution)
    args = (*laser, *caster.kernel_args(angles), du, dv, *(np.empty(angles.size) for _ in range(4)))

    def cast(poses) -> np.ndarray:
        poses = np.ascontiguousarray(np.atleast_2d(np.asarray(poses, dtype=float)))
        caster.prepare(poses, laser)  # a large map's table: build the tiles in use
        out = np.empty((poses.shape[0], angles.size))
        cast_rows(poses, *args, out)
        return out
    return cast
