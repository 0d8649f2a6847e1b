"""Likelihood-field sensor model (Thrun, Burgard, Fox: Probabilistic Robotics §6.4; nav2_amcl's
``likelihood_field`` and ``likelihood_field_prob``).

No ray is cast. Each beam b (measured range z_b, bearing a_b in the laser frame) is projected from
the particle's laser pose (x_l, y_l, θ_l) to its end point

    e_b = (x_l + z_b·cos(θ_l + a_b),  y_l + z_b·sin(θ_l + a_b))

and scored by d_b, the end point's distance (m) to the nearest *occupied* cell, read from a
distance field of the map precomputed once (Euclidean distance transform, cell centres,
capped at ``laser_likelihood_max_dist``; an end point off the map counts as that cap):

    p(z_b | x) = z_hit · exp(−d_b² / (2 σ_hit²)) + z_rand / z_max

with σ_hit = ``lf_sigma_hit`` (m) and z_max (m) the sensor's range: ``laser_max_range`` when > 0,
else the scan's ``range_max`` (``log_likelihood(..., range_max=)``), else ``UNKNOWN_RANGE_MAX``
(``sensors.resolve_max_range``). As in nav2_amcl the Gaussian is *not* normalised (its peak is
z_hit), so nav2's values of z_hit, z_rand, σ_hit mean the same here. Beams at or beyond z_max, and
NaN/inf beams ("no return"), are skipped (they say nothing about where an obstacle is). The same
beams are skipped for every particle, so skipping never favours one.

Combination over beams: the product, as in the beam model and nav2's ``likelihood_field_prob``,
evaluated as a sum of logs and squashed by the same ``squash_factor``:

    log w = (Σ_b log p(z_b | x)) / squash_factor

(nav2's plain ``likelihood_field`` instead scores 1 + Σ_b p³, an ad-hoc sum that is never 0
and flattens the peak; the squashed product keeps the package's log-space pipeline — the
filter's normalisation, health's mean log-likelihood, replay — identical for both models, and
the squash plays the role nav2's cube-sum plays: it tempers over-confident beams.)
Particles off the map or in an occupied cell get −inf, as in the beam model.

Per-cell precomputation: the field stores each cell's capped distance quantised to one byte,

    q(cell) = round(d / Δ),   Δ = laser_likelihood_max_dist / 255   (≤ 4 mm at the 2 m default)

and a 256-entry table ℓ[q] = log(z_hit·exp(−(qΔ)²/2σ²) + z_rand/z_max) (one per z_max, cached), so each beam costs one
byte look-up, one table look-up and one add; off the map q = 255 (the cap). 1 byte per cell
keeps the field in cache and large maps small. q = 0 exactly on occupied cells (every other
cell is at least one resolution away), so the same grid says which particles are in walls.

Beam skipping (``do_beamskip``, nav2's ``likelihood_field_prob``): with many particles a beam
that hits an unmapped obstacle agrees with the map for few of them. A beam is *used* when the
fraction of particles whose end point lies within ``beam_skip_distance`` of an obstacle exceeds
``beam_skip_threshold``; if the skipped beams reach ``beam_skip_error_threshold`` of the beams
used, the cloud itself is off and every beam is used. Particles off the map or in walls do not
vote (nav2 counts them too; they get −inf anyway).

Deskew (a sweeping lidar, ``offsets`` δ_b = (dx_b, dy_b, dθ_b): the laser's own motion until
beam b's time, the same for every particle): the end point in the laser frame becomes
(dx_b, dy_b) + z_b·(cos, sin)(a_b + dθ_b), computed once per scan, so deskewing costs nothing.

``log_likelihood`` runs a compiled (numba) pass per particle with no (N, B) temporaries;
``log_likelihood_numpy`` is its numpy reference, asserted equal in ``test_likelihood_field.py``.
"""
from __future__ import annotations

import math
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, fields, replace

import numpy as np

from localization.core.cost import CostMeter
from localization.core.models.sensor import LaserMount, Preparation, beam_mask, resolve_max_range, skips_beams
from localization.core.occupancy_map import OccupancyMap
from localization.core.parameters import default
from localization.core.raycast.kernels import HAVE_NUMBA

if HAVE_NUMBA:
    from numba import njit

QUANT_MAX = 255  # the quantised distance of the cap (uint8)
BAND_CELLS = 2_000_000  # cells per band of the distance transform (bounds its temporaries)
UNKNOWN_RANGE_MAX = 30.0  # m: z_max when neither laser_max_range nor the scan gives one (a Hokuyo UST-10LX's)


@dataclass(frozen=True)
class LikelihoodFieldParams:
    """The likelihood field's parameters; names and meanings as in the parameter table."""

    lf_z_hit: float = default("lf_z_hit")
    lf_z_rand: float = default("lf_z_rand")
    lf_sigma_hit: float = default("lf_sigma_hit")  # m
    laser_likelihood_max_dist: float = default("laser_likelihood_max_dist")  # m
    laser_max_range: float = default("laser_max_range")  # m; <= 0: the scan's range_max
    do_beamskip: bool = default("do_beamskip")
    beam_skip_distance: float = default("beam_skip_distance")  # m
    beam_skip_threshold: float = default("beam_skip_threshold")
    beam_skip_error_threshold: float = default("beam_skip_error_threshold")
    beam_skip_max_spread: float = default("beam_skip_max_spread")  # m
    squash_factor: float = default("squash_factor")
    num_beams_per_particle: int = default("num_beams_per_particle")
    scan_field_of_view: float = default("scan_field_of_view")  # rad
    laser_offset_x: float = default("laser_offset_x")  # m, in base_link
    laser_offset_y: float = default("laser_offset_y")  # m
    laser_offset_yaw: float = default("laser_offset_yaw")  # rad

    @classmethod
    def from_parameters(cls, params) -> "LikelihoodFieldParams":
        """From a ``Parameters`` mapping (the node's, replay's): same names."""
        return cls(**{f.name: params[f.name] for f in fields(cls)})


class LikelihoodFieldModel(LaserMount):
    """``LikelihoodFieldModel(**overrides)`` or ``LikelihoodFieldModel(params)``; a
    ``sensors.SensorModel``, as ``BeamModel``."""

    supports_deskew = True  # log_likelihood takes per-beam laser offsets (a deskewed sweep)
    supports_range_scale = False  # casts no ranges: the range scale cannot be learnt (range_probe)

    def __init__(self, params: LikelihoodFieldParams | None = None, *, occupancy_map: OccupancyMap | None = None,
                 laser_offset=None, use_numba: bool = HAVE_NUMBA, **overrides):
        if laser_offset is not None:
            ox, oy, oyaw = (float(v) for v in laser_offset)
            overrides.update(laser_offset_x=ox, laser_offset_y=oy, laser_offset_yaw=oyaw)
        self.params = p = replace(params or LikelihoodFieldParams(), **overrides)
        if not (p.lf_z_hit >= 0 and p.lf_z_rand >= 0 and p.lf_z_hit + p.lf_z_rand > 0):
            raise ValueError(f"lf_z_hit ({p.lf_z_hit}) and lf_z_rand ({p.lf_z_rand}) must be >= 0, not both 0")
        if not (p.lf_sigma_hit > 0 and p.laser_likelihood_max_dist > 0 and p.squash_factor > 0):
            raise ValueError("lf_sigma_hit, laser_likelihood_max_dist and squash_factor must be > 0")
        if not math.isfinite(p.laser_max_range):
            raise ValueError(f"laser_max_range must be finite (<= 0: the scan's range_max), got {p.laser_max_range}")
        self.use_numba = bool(use_numba) and HAVE_NUMBA
        self.map: OccupancyMap | None = None
        self.field: np.ndarray | None = None  # (H, W) uint8: q(cell), the quantised capped distance
        self.step = p.laser_likelihood_max_dist / QUANT_MAX  # m per quantum Δ
        q = np.arange(QUANT_MAX + 1)
        self._log_tables: dict = {}  # z_max -> (256,) ℓ[q]
        self.near_table = q * self.step < p.beam_skip_distance  # (256,) do_beamskip: end point near an obstacle
        self.last_beams_used: int | None = None  # beams used by the last evaluation (after max range / skipping)
        self.cost = CostMeter()  # beam skipping's extra work (``core.cost``; a localizer shares its meter)
        if occupancy_map is not None:
            self.set_map(occupancy_map)

    # ------------------------------------------------------------------ the laser
    # the laser pose: LaserMount (laser_offset, set_laser_offset)

    # ------------------------------------------------------------------ the field
    @property
    def max_range(self) -> float:
        """z_max (m) when the scan gives no range_max: ``laser_max_range`` if > 0, else
        ``UNKNOWN_RANGE_MAX``."""
        return self.max_range_for(None)

    def max_range_for(self, range_max: float | None) -> float:
        """z_max (m) for a scan with this ``range_max``: beams at or beyond it are skipped; the
        uniform density is z_rand / z_max."""
        return resolve_max_range(self.params.laser_max_range, range_max, UNKNOWN_RANGE_MAX)

    def log_p(self, distance, z_max: float | None = None) -> np.ndarray:
        """ℓ(d) = log(z_hit·exp(−d²/2σ²) + z_rand/z_max), d in metres (capped); z_max default ``max_range``."""
        p = self.params
        z_max = self.max_range if z_max is None else float(z_max)
        d = np.minimum(np.asarray(distance, dtype=float), p.laser_likelihood_max_dist)
        with np.errstate(divide="ignore"):
            return np.log(p.lf_z_hit * np.exp(-0.5 * (d / p.lf_sigma_hit) ** 2) + p.lf_z_rand / z_max)

    def log_table_for(self, z_max: float) -> np.ndarray:
        """(256,) ℓ[q] for this z_max (cached); floored at log(tiny) so z_rand = 0 with a far end point
        is very unlikely, not impossible."""
        table = self._log_tables.get(z_max)
        if table is None:
            q = np.arange(QUANT_MAX + 1)
            table = self._log_tables[z_max] = np.maximum(self.log_p(q * self.step, z_max),
                                                         np.log(np.finfo(float).tiny))
        return table

    @property
    def log_table(self) -> np.ndarray:
        """ℓ[q] at ``max_range`` (a scan without range_max)."""
        return self.log_table_for(self.max_range)

    def distance_field(self, occupancy_map: OccupancyMap) -> np.ndarray:
        """(H, W) float32: distance (m) of each cell centre to the nearest occupied cell centre, capped
        at laser_likelihood_max_dist (nav2's occ_dist). A map with no occupied cell: the cap everywhere."""
        from scipy.ndimage import distance_transform_edt
        cap = self.params.laser_likelihood_max_dist
        occupied = occupancy_map.occupied
        out = np.full(occupied.shape, cap, dtype=np.float32)
        # bands of rows, each transformed with a margin of the cap: a capped distance only depends on the
        # obstacles within the cap, and the transform's temporaries stay small on large maps
        h, w = occupied.shape
        margin = int(math.ceil(cap / occupancy_map.resolution)) + 1
        band = max(1, BAND_CELLS // max(w, 1))
        for r0 in range(0, h, band):
            r1 = min(h, r0 + band)
            a0, a1 = max(0, r0 - margin), min(h, r1 + margin)
            block = occupied[a0:a1]
            if block.any():
                d = distance_transform_edt(~block)[r0 - a0:r1 - a0] * occupancy_map.resolution
                out[r0:r1] = np.minimum(d, cap)
        return out

    def prepare(self, occupancy_map: OccupancyMap) -> np.ndarray:
        """The quantised field q of a map (the slow part of ``set_map``), without touching the model:
        a caller may build it on another thread, then call ``set_map(occupancy_map, field)``."""
        d = self.distance_field(occupancy_map)
        field = np.rint(d / np.float32(self.step)).astype(np.uint8)
        field[occupancy_map.occupied] = 0
        field[(field == 0) & ~occupancy_map.occupied] = 1  # only walls are 0 (a tiny cap could round to 0)
        return np.ascontiguousarray(field)

    def preparation(self, occupancy_map: OccupancyMap) -> Preparation:
        """The distance field is computed in ``prepare`` (a fraction of a second per million cells)."""
        return Preparation(False, f"likelihood field: distance transform of the map {occupancy_map.width}x"
                                  f"{occupancy_map.height} cells (capped at {self.params.laser_likelihood_max_dist} m)")

    def set_map(self, occupancy_map: OccupancyMap, prepared=None) -> None:
        """Use a (new) map: precompute the quantised distance field (or take ``prepared``, from
        ``prepare``); compile."""
        if prepared is None:
            prepared = self.prepare(occupancy_map)
        self.field = prepared
        self.map = occupancy_map
        if self.use_numba:  # compile (or load from numba's cache) now, not on the first scan
            self.log_likelihood(np.zeros((1, 3)), np.ones(1), np.zeros(1))

    @property
    def nbytes(self) -> int:
        """Memory of the precomputed field (bytes): one per cell."""
        return 0 if self.field is None else int(self.field.nbytes)

    def scratch(self) -> AbstractContextManager:
        """No temporary memory: the field is whole."""
        return nullcontext()

    def locality_order(self, xy) -> np.ndarray:
        """The identity: the field has no parts to keep together."""
        return np.arange(len(np.asarray(xy).reshape(-1, 2)))

    def range_probe(self, angles, offsets=None, range_max=None):
        raise ValueError("the likelihood field casts no ranges: it cannot learn the range scale")

    def set_range_scale(self, scale: float) -> None:
        raise ValueError("the likelihood field has no range scale to set (lidar_scale_to_map_scale is unused)")

    # ------------------------------------------------------------------ evaluation
    def default_angles(self, num_beams: int) -> np.ndarray:
        """The course convention: beams evenly over ``scan_field_of_view`` centred on the heading."""
        half = 0.5 * self.params.scan_field_of_view
        return np.linspace(-half, half, num_beams)

    def _inputs(self, particles, ranges, angles, offsets=None, z_max=None):
        if self.map is None:
            raise RuntimeError("the sensor model has no map yet: call set_map() first")
        particles = np.ascontiguousarray(np.atleast_2d(np.asarray(particles, dtype=float)))
        ranges = np.asarray(ranges, dtype=float).ravel()
        angles = self.default_angles(ranges.size) if angles is None else np.asarray(angles, dtype=float).ravel()
        if angles.size != ranges.size:
            raise ValueError(f"{ranges.size} ranges but {angles.size} angles")
        with np.errstate(invalid="ignore"):
            used = np.isfinite(ranges) & np.isfinite(angles) & (ranges < z_max) & (ranges >= 0)
        # end points in the laser frame, in map cells: e = laser + R(θ_l)·(z cos a, z sin a); a deskewed
        # sweep (offsets δ_b = (dx, dy, dθ) of the laser at beam b's time): (dx, dy) + z (cos, sin)(a + dθ)
        res = self.map.resolution
        z, a = ranges[used], angles[used]
        dx = dy = 0.0
        if offsets is not None:
            offsets = np.asarray(offsets, dtype=float).reshape(-1, 3)
            if offsets.shape[0] == ranges.size and np.all(np.isfinite(offsets)):
                dx, dy, a = offsets[used, 0], offsets[used, 1], a + offsets[used, 2]
        local = np.stack([dx + z * np.cos(a), dy + z * np.sin(a)], axis=1) / res
        return particles, np.ascontiguousarray(local)

    def _grid_frame(self):
        """(ox, oy, cos, sin, resolution, yaw) of the map: grid = R(−yaw)·(world − origin) / resolution."""
        ox, oy, yaw = self.map.origin
        return float(ox), float(oy), math.cos(yaw), math.sin(yaw), float(self.map.resolution), float(yaw)

    def log_likelihood(self, particles, ranges, angles=None, offsets=None, range_max=None) -> np.ndarray:
        """Squashed log weights (N,): Σ over used beams of ℓ(end point) / squash_factor;
        −inf for particles off the map or in an occupied cell. ``offsets`` (B, 3): per-beam laser
        motion of a deskewed sweep (folded into the laser-frame end points: no extra cost);
        ``range_max``: the scan's (m), z_max when ``laser_max_range`` <= 0."""
        if not self.use_numba:
            return self.log_likelihood_numpy(particles, ranges, angles, offsets, range_max)
        z_max = self.max_range_for(range_max)
        particles, local = self._inputs(particles, ranges, angles, offsets, z_max)
        n = particles.shape[0]
        ox, oy, c, s, res, yaw = self._grid_frame()
        off = self.laser_offset
        log_table = self.log_table_for(z_max)
        args = (particles, float(off[0]), float(off[1]), float(off[2]), ox, oy, c, s, res, yaw, self.field,
                log_table, local[:, 0].copy(), local[:, 1].copy())
        out = np.empty(n)
        if self.params.do_beamskip:
            self.cost.sweep("beam_skip", 6)  # skips_beams: isfinite, all, the selection, the std
        if not skips_beams(particles, self.params) or local.shape[0] == 0:
            _lf_kernel(*args, out)
            self.last_beams_used = local.shape[0]
        else:
            per_beam = np.empty((n, local.shape[0]), dtype=np.uint8)
            votes = np.zeros(local.shape[0], dtype=np.int64)
            _lf_beamskip_kernel(*args, self.near_table, per_beam, votes, out)
            mask = beam_mask(self.params, votes, int(np.isfinite(out).sum()))
            self.last_beams_used = int(mask.sum())
            _masked_sum(per_beam, log_table, mask, out)
            self.cost.cast("beam_skip", per_beam.size)  # the compiled sum over the used beams
        out[np.isfinite(out)] /= self.params.squash_factor
        return out

    def log_likelihood_numpy(self, particles, ranges, angles=None, offsets=None, range_max=None) -> np.ndarray:
        """``log_likelihood`` in numpy, (N, B) temporaries: the reference of the compiled kernels."""
        z_max = self.max_range_for(range_max)
        particles, local = self._inputs(particles, ranges, angles, offsets, z_max)
        ox, oy, c, s, res, yaw = self._grid_frame()
        off = self.laser_offset
        # laser pose of every particle, then in grid coordinates
        pc, ps = np.cos(particles[:, 2]), np.sin(particles[:, 2])
        lx = particles[:, 0] + pc * off[0] - ps * off[1]
        ly = particles[:, 1] + ps * off[0] + pc * off[1]
        gx0 = (c * (lx - ox) + s * (ly - oy)) / res
        gy0 = (-s * (lx - ox) + c * (ly - oy)) / res
        phi = particles[:, 2] + off[2] - yaw
        fc, fs = np.cos(phi)[:, None], np.sin(phi)[:, None]
        ex = gx0[:, None] + fc * local[:, 0] - fs * local[:, 1]
        ey = gy0[:, None] + fs * local[:, 0] + fc * local[:, 1]
        h, w = self.field.shape
        with np.errstate(invalid="ignore"):
            inside = (ex >= 0) & (ex < w) & (ey >= 0) & (ey < h)
        col = np.where(inside, np.floor(np.where(inside, ex, 0)), 0).astype(np.intp)
        row = np.where(inside, np.floor(np.where(inside, ey, 0)), 0).astype(np.intp)
        q = np.where(inside, self.field[row, col], QUANT_MAX)
        # the particle itself (not its laser) must be in a non-occupied cell of the map
        bad = self.map.is_occupied_or_outside(particles[:, :2])
        mask = np.ones(local.shape[0], dtype=bool)
        if skips_beams(particles, self.params) and local.shape[0]:
            votes = (self.near_table[q] & ~bad[:, None]).sum(axis=0)
            mask = beam_mask(self.params, votes, int((~bad).sum()))
        out = self.log_table_for(z_max)[q[:, mask]].sum(axis=1) / self.params.squash_factor
        out[bad] = -np.inf
        return out

    def evaluate(self, particles, ranges, angles=None, range_max=None) -> np.ndarray:
        """Weights (N,): Π_b p(z_b | x) ^ (1/squash_factor). Never NaN; 0 where impossible."""
        with np.errstate(under="ignore"):
            return np.exp(self.log_likelihood(particles, ranges, angles, range_max=range_max))


if HAVE_NUMBA:
    @njit(cache=True, nogil=True, inline="always")
    def _laser_in_grid(px, py, pth, off_x, off_y, off_th, map_ox, map_oy, map_c, map_s, resolution, map_yaw):
        c = math.cos(pth)
        s = math.sin(pth)
        lx = px + c * off_x - s * off_y - map_ox
        ly = py + s * off_x + c * off_y - map_oy
        phi = pth + off_th - map_yaw
        return (map_c * lx + map_s * ly) / resolution, (-map_s * lx + map_c * ly) / resolution, \
            math.cos(phi), math.sin(phi)

    @njit(cache=True, nogil=True, inline="always")
    def _particle_ok(px, py, map_ox, map_oy, map_c, map_s, resolution, field):
        """In the map and not in an occupied cell (q = 0)."""
        h, w = field.shape
        dx = px - map_ox
        dy = py - map_oy
        gx = (map_c * dx + map_s * dy) / resolution
        gy = (-map_s * dx + map_c * dy) / resolution
        if not (gx >= 0.0 and gx < w and gy >= 0.0 and gy < h):  # off the map (or NaN)
            return False
        return field[int(math.floor(gy)), int(math.floor(gx))] != 0

    @njit(cache=True, nogil=True)
    def _lf_kernel(particles, off_x, off_y, off_th, map_ox, map_oy, map_c, map_s, resolution, map_yaw,
                   field, log_table, local_x, local_y, out):  # pragma: no cover - compiled
        """out[i] = Σ_b ℓ[q(end point b of particle i)] (not yet squashed); −inf off the map / in walls."""
        h, w = field.shape
        n_beams = local_x.size
        log_off = log_table[QUANT_MAX]
        for i in range(particles.shape[0]):
            px = particles[i, 0]
            py = particles[i, 1]
            if not _particle_ok(px, py, map_ox, map_oy, map_c, map_s, resolution, field):
                out[i] = -np.inf
                continue
            gx, gy, fc, fs = _laser_in_grid(px, py, particles[i, 2], off_x, off_y, off_th, map_ox, map_oy,
                                            map_c, map_s, resolution, map_yaw)
            total = 0.0
            for b in range(n_beams):
                ex = gx + fc * local_x[b] - fs * local_y[b]
                ey = gy + fs * local_x[b] + fc * local_y[b]
                if ex >= 0.0 and ex < w and ey >= 0.0 and ey < h:
                    total += log_table[field[int(math.floor(ey)), int(math.floor(ex))]]
                else:
                    total += log_off
            out[i] = total

    @njit(cache=True, nogil=True)
    def _lf_beamskip_kernel(particles, off_x, off_y, off_th, map_ox, map_oy, map_c, map_s, resolution, map_yaw,
                            field, log_table, local_x, local_y, near_table, per_beam, votes,
                            out):  # pragma: no cover - compiled
        """As ``_lf_kernel``, keeping each beam's q in per_beam[i, b] and counting, per beam, the valid
        particles whose end point is near an obstacle (votes[b]); out[i] = 0 (valid) or −inf."""
        h, w = field.shape
        n_beams = local_x.size
        for i in range(particles.shape[0]):
            px = particles[i, 0]
            py = particles[i, 1]
            if not _particle_ok(px, py, map_ox, map_oy, map_c, map_s, resolution, field):
                out[i] = -np.inf
                continue
            out[i] = 0.0
            gx, gy, fc, fs = _laser_in_grid(px, py, particles[i, 2], off_x, off_y, off_th, map_ox, map_oy,
                                            map_c, map_s, resolution, map_yaw)
            for b in range(n_beams):
                ex = gx + fc * local_x[b] - fs * local_y[b]
                ey = gy + fs * local_x[b] + fc * local_y[b]
                q = QUANT_MAX
                if ex >= 0.0 and ex < w and ey >= 0.0 and ey < h:
                    q = field[int(math.floor(ey)), int(math.floor(ex))]
                per_beam[i, b] = q
                if near_table[q]:
                    votes[b] += 1

    @njit(cache=True, nogil=True)
    def _masked_sum(per_beam, log_table, mask, out):  # pragma: no cover - compiled
        """out[i] = Σ_{b: mask[b]} ℓ[per_beam[i, b]] where out[i] is finite (a valid particle)."""
        for i in range(per_beam.shape[0]):
            if out[i] == -np.inf:
                continue
            total = 0.0
            for b in range(per_beam.shape[1]):
                if mask[b]:
                    total += log_table[per_beam[i, b]]
            out[i] = total
else:  # pragma: no cover
    _lf_kernel = _lf_beamskip_kernel = _masked_sum = None
